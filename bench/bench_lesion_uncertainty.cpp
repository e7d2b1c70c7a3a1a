// The lesions' confidence regions (pipeline/lesion_uncertainty.h, docs/uncertainty.md): the nominal
// run, the region of an ensemble of --samples runs, and how well it holds the lesion positions of
// --validation further runs drawn from the same ranges (later points of the same Halton sequence);
// then each source alone (stiffness, Poisson ratio, path) with the others at their nominal values,
// and the ensemble's cost against the single run. Every ensemble is given the nominal run (its
// multigrid levels, and the start of each sample's recovery of X0), as the CLI and the node give it;
// the first one runs again without it, the reference: its cost and how far its lesions lie from the
// reused ones. Prints tables; --json FILE writes the same figures.
//   bench_lesion_uncertainty [--case config/phantom_default.yaml] [--elements 8000] [--samples 8]
//                            [--validation 24] [--no-sources] [--json FILE]
// The case's maps give everything else (its `uncertainty:` ranges and confidence included).
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/pipeline/case_file.h"
#include "breast_sim/core/pipeline/lesion_uncertainty.h"

using namespace breast_sim::core;
namespace bench = breast_sim::bench;

namespace {

// Mahalanobis radius of p under a region (infinite off a degenerate region's span).
double mahalanobis(const LesionRegion& r, const Eigen::Vector3d& p) {
  const Eigen::Vector3d d = r.axes.transpose() * (p - r.centre_m);
  double s = 0;
  for (int k = 0; k < 3; ++k) {
    const double sigma = r.scale > 0 ? r.semi_axes_m(k) / r.scale : 0.0;
    if (sigma > 1e-12) s += (d(k) / sigma) * (d(k) / sigma);
    else if (std::abs(d(k)) > 1e-9) return std::numeric_limits<double>::infinity();
  }
  return std::sqrt(s);
}

nlohmann::json regionJson(const LesionRegion& r) {
  return {{"semi_axes_mm", {r.semi_axes_m.x() * 1e3, r.semi_axes_m.y() * 1e3, r.semi_axes_m.z() * 1e3}},
          {"max_sample_distance_mm", r.max_sample_distance_m * 1e3},
          {"rms_distance_mm", std::sqrt(r.covariance_m2.trace()) * 1e3}};
}

}  // namespace

int main(int argc, char** argv) {
  std::string case_path = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml", json_path;
  int elements = 8000, samples = 8, validation = 24;
  bool sources = true;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--case") case_path = bench::argValue(argc, argv, i);
    else if (a == "--elements") elements = std::stoi(bench::argValue(argc, argv, i));
    else if (a == "--samples") samples = std::stoi(bench::argValue(argc, argv, i));
    else if (a == "--validation") validation = std::stoi(bench::argValue(argc, argv, i));
    else if (a == "--no-sources") sources = false;
    else if (a == "--json") json_path = bench::argValue(argc, argv, i);
    else {
      std::fprintf(stderr,
                   "usage: bench_lesion_uncertainty [--case FILE] [--elements N] [--samples N] [--validation N] "
                   "[--no-sources] [--json FILE]\n");
      return 2;
    }
  }
  ModelCase c = loadModelCase(case_path);
  if (!c.mesh) c.meshing.target_elements = elements;
  auto t0 = bench::Clock::now();
  const SimulationModel model = buildSimulationModel(c);
  const double mesh_s = bench::since(t0);
  PipelineSettings settings = loadPipelineSettings(case_path);
  settings.uncertainty.samples = samples;
  settings.uncertainty.validate();
  const UncertaintySettings& u = settings.uncertainty;
  std::printf("case %s: %d elements, %zu lesions (meshed in %.1f s); E x [%.2f, %.2f], nu [%.3f, %.3f], "
              "time steps x [%.2f, %.2f], confidence %.2f\n",
              c.name.c_str(), model.mesh.numTets(), model.lesions.size(), mesh_s, u.youngs_modulus_factor_min,
              u.youngs_modulus_factor_max, u.poisson_ratio_min, u.poisson_ratio_max, u.time_step_factor_min,
              u.time_step_factor_max, u.confidence);
  if (model.lesions.empty()) {
    std::fprintf(stderr, "the case has no lesions\n");
    return 2;
  }

  t0 = bench::Clock::now();
  ProneToSupinePipeline nominal(c, model, settings);
  nominal.run();
  const double nominal_s = bench::since(t0);
  const Points p0 = nominal.lesionPositions();
  const bool nominal_ok = nominal.gravityReport().converged &&
                          (!nominal.morphingReport().ran || nominal.morphingReport().converged);
  std::printf("nominal run: %.2f s%s\n", nominal_s, nominal_ok ? "" : " (a stage did not converge)");

  const LesionUncertainty ens = estimateLesionUncertainty(c, model, settings, p0, {}, nullptr, 1, &nominal);
  if (!ens.valid) {
    std::fprintf(stderr, "ensemble not valid: %s\n", ens.failure.c_str());
    return 3;
  }
  PipelineSettings vs = settings;
  vs.uncertainty.samples = validation;
  const LesionUncertainty val = estimateLesionUncertainty(c, model, vs, p0, {}, nullptr, samples + 1, &nominal);
  if (!val.valid) {
    std::fprintf(stderr, "validation ensemble not valid: %s\n", val.failure.c_str());
    return 3;
  }

  nlohmann::json out;
  out["case"] = c.name;
  out["elements"] = model.mesh.numTets();
  out["samples"] = samples;
  out["validation_samples"] = validation;
  out["confidence"] = u.confidence;
  out["seconds"] = {{"nominal", nominal_s}, {"ensemble", ens.seconds}, {"validation", val.seconds}};
  out["cost_vs_run"] = ens.seconds / nominal_s;

  std::printf("\n%d-sample regions (%.0f%%) and %d further samples\n", samples, 100 * u.confidence, validation);
  std::printf("%-14s %26s %10s %10s %12s %12s %26s\n", "lesion", "semi-axes [mm]", "max [mm]", "inside",
              "max radius", "radius p50", "pooled semi-axes [mm]");
  int inside_all = 0, total_all = 0;
  nlohmann::json jl = nlohmann::json::array();
  for (size_t l = 0; l < model.lesions.size(); ++l) {
    const LesionRegion& r = ens.lesions[l];
    int inside = 0;
    std::vector<double> radii;
    std::vector<Eigen::Vector3d> pooled;
    for (const auto& s : ens.samples) pooled.push_back(s.lesions_m.row(static_cast<Eigen::Index>(l)).transpose());
    for (const auto& s : val.samples) {
      const Eigen::Vector3d p = s.lesions_m.row(static_cast<Eigen::Index>(l)).transpose();
      inside += r.contains(p);
      radii.push_back(mahalanobis(r, p) / r.scale);  // 1 = on the region's boundary
      pooled.push_back(p);
    }
    const LesionRegion all = lesionRegion(p0.row(static_cast<Eigen::Index>(l)).transpose(), pooled, u.confidence);
    inside_all += inside;
    total_all += validation;
    const double rmax = *std::max_element(radii.begin(), radii.end());
    std::printf("%-14s %8.2f %8.2f %8.2f %10.2f %5d/%-4d %12.2f %12.2f %8.2f %8.2f %8.2f\n", model.lesions[l].name.c_str(),
                r.semi_axes_m.x() * 1e3, r.semi_axes_m.y() * 1e3, r.semi_axes_m.z() * 1e3, r.max_sample_distance_m * 1e3,
                inside, validation, rmax, bench::median(radii), all.semi_axes_m.x() * 1e3, all.semi_axes_m.y() * 1e3,
                all.semi_axes_m.z() * 1e3);
    jl.push_back({{"name", model.lesions[l].name}, {"region", regionJson(r)}, {"validation_inside", inside},
                  {"validation_max_radius", rmax}, {"validation_median_radius", bench::median(radii)},
                  {"pooled_region", regionJson(all)}});
  }
  out["lesions"] = jl;
  out["coverage"] = static_cast<double>(inside_all) / total_all;
  std::printf("coverage: %d of %d further positions inside their lesion's region (%.0f%%); radius: Mahalanobis "
              "distance / region scale (1 = on the boundary)\n",
              inside_all, total_all, 100.0 * inside_all / total_all);

  if (sources) {
    // Each source alone: the others at the nominal values.
    struct Source {
      const char* name;
      UncertaintySettings s;
    };
    const double nu = settings.simulation.material.poisson_ratio;
    std::vector<Source> list(3, {"", u});
    list[0].name = "stiffness";
    list[1].name = "poisson_ratio";
    list[2].name = "path";
    for (int k = 0; k < 3; ++k) {
      UncertaintySettings& s = list[static_cast<size_t>(k)].s;
      if (k != 0) s.youngs_modulus_factor_min = s.youngs_modulus_factor_max = 1.0;
      if (k != 1) s.poisson_ratio_min = s.poisson_ratio_max = nu;
      if (k != 2) s.time_step_factor_min = s.time_step_factor_max = 1.0;
    }
    std::printf("\neach source alone (%d samples, the others nominal): rms and largest distance from the nominal "
                "position [mm]\n%-14s", samples, "lesion");
    for (const auto& src : list) std::printf(" %20s", src.name);
    std::printf("\n");
    std::vector<LesionUncertainty> runs;
    for (const auto& src : list) {
      PipelineSettings ss = settings;
      ss.uncertainty = src.s;
      runs.push_back(estimateLesionUncertainty(c, model, ss, p0, {}, nullptr, 1, &nominal));
      if (!runs.back().valid) {
        std::fprintf(stderr, "source %s: ensemble not valid: %s\n", src.name, runs.back().failure.c_str());
        return 3;
      }
    }
    nlohmann::json js;
    for (size_t l = 0; l < model.lesions.size(); ++l) {
      std::printf("%-14s", model.lesions[l].name.c_str());
      for (size_t k = 0; k < list.size(); ++k) {
        const LesionRegion& r = runs[k].lesions[l];
        std::printf(" %9.2f %10.2f", std::sqrt(r.covariance_m2.trace()) * 1e3, r.max_sample_distance_m * 1e3);
        js[list[k].name][model.lesions[l].name] = regionJson(r);
      }
      std::printf("\n");
    }
    out["sources"] = js;
  }
  std::printf("\ncost: nominal run %.2f s, %d-sample ensemble %.2f s (%.1fx the run), %d further samples %.2f s\n",
              nominal_s, samples, ens.seconds, ens.seconds / nominal_s, validation, val.seconds);

  // The reference: the same ensemble with every sample on its own (levels meshed, X0 from prone).
  const LesionUncertainty fresh = estimateLesionUncertainty(c, model, settings, p0);
  if (!fresh.valid) {
    std::fprintf(stderr, "ensemble without the nominal run not valid: %s\n", fresh.failure.c_str());
    return 3;
  }
  int loadings = 0, fresh_loadings = 0;
  double gap = 0.0;
  for (size_t k = 0; k < ens.samples.size(); ++k) {
    loadings += ens.samples[k].unloaded_loadings;
    fresh_loadings += fresh.samples[k].unloaded_loadings;
    gap = std::max(gap, (ens.samples[k].lesions_m - fresh.samples[k].lesions_m).rowwise().norm().maxCoeff());
  }
  std::printf("%-30s %12s %20s %12s\n", "ensemble", "seconds", "X0 loadings (all)", "x the run");
  std::printf("%-30s %12.2f %20d %12.1f\n", "given the nominal run", ens.seconds, loadings, ens.seconds / nominal_s);
  std::printf("%-30s %12.2f %20d %12.1f\n", "every sample on its own", fresh.seconds, fresh_loadings,
              fresh.seconds / nominal_s);
  std::printf("the samples' lesions of the two lie within %.4f mm of each other\n", gap * 1e3);
  out["seconds"]["ensemble_without_nominal_run"] = fresh.seconds;
  out["unloaded_loadings"] = {{"given_nominal_run", loadings}, {"without", fresh_loadings}};
  out["cost_vs_run_without_nominal_run"] = fresh.seconds / nominal_s;
  out["sample_lesion_gap_mm"] = gap * 1e3;
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << '\n';
  return 0;
}
