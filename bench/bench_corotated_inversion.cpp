// Why do co-rotated linear tetrahedra invert elements under the supine load, and why does their
// error against a finite-strain reference grow with refinement? (docs/speed_accuracy.md)
//
// The phantom of a case is meshed at --target elements (cached with the references, so reruns use
// the same mesh), loaded with g_supine − g_prone (or --load hanging) and settled like
// bench_speed_accuracy does (settle(), CHOLMOD, so no solver error), under variations:
//   dt (settling time step), load scale, load stepping (quasi-static continuation), volumetric term
//   of the co-rotated material (tr S − 3 of classic co-rotated linear elasticity against J − 1).
// Per run: settled?, steps, the first step with an inverted element, inverted elements at the end,
// largest displacement, volume change, and (at full load) the mean nodal error against the cached
// CalculiX reference. Then, for the baseline run, where the inverted and collapsed elements are
// (touching the fixed chest wall? on the skin?), their rest quality, their signed singular values,
// J = det F and tr S, and how far rotationOf is from the SVD rotation on them; and the per-element
// J = det F distribution of ours, linear FEM and the reference (on the reference's own mesh).
//
//   bench_corotated_inversion [--case FILE] [--load supine|hanging] [--target 5000]
//        [--reference-target 99390] [--reference-element c3d4] [--cache DIR] [--json FILE]
//        [--quick]  (only the baseline, the J − 1 variant and stiffening with either)
#include <algorithm>
#include <cstdio>
#include <fstream>
#include <set>
#include <string>
#include <vector>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/polar_decomposition.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/reference/calculix.h"
#include "breast_sim/core/reference/error_metrics.h"
#include "breast_sim/core/reference/reference_case.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

/// One variation of the settling run.
struct Variant {
  std::string name;
  std::string formulation = "corotated";  // corotated | linear
  CorotatedTetFem::VolumeTerm volume = CorotatedTetFem::VolumeTerm::kTrace;
  double dt_s = 0.33;
  double load_scale = 1.0;
  int load_increments = 1;  // quasi-static continuation: settle at scale k/n, k = 1..n
  double increment_tolerance_m = 1e-5;
  int max_steps = 400;
  bool stiffening = false;  // von Mises stiffening with time-step reversal (material/stiffening.h)
};

struct RunResult {
  Points u;
  bool settled = true;
  int steps = 0;
  int first_inverted_step = -1;  // settling step (summed over increments) with the first inversion
  int max_inverted = 0;
  int inverted = 0;
  double seconds = 0;
};

/// Deformation gradient of element e at positions x.
Eigen::Matrix3d deformationGradient(const TetMesh& mesh, const Points& x, int e) {
  Eigen::Matrix3d Dm, Ds;
  const auto& t = mesh.tets();
  for (int k = 0; k < 3; ++k) {
    Dm.col(k) = (mesh.nodes().row(t(e, k + 1)) - mesh.nodes().row(t(e, 0))).transpose();
    Ds.col(k) = (x.row(t(e, k + 1)) - x.row(t(e, 0))).transpose();
  }
  return Ds * Dm.inverse();
}

RunResult runVariant(const ModelCase& c, const SimulationModel& m, SimulationSettings s, const Eigen::Vector3d& g,
                     const Variant& v) {
  s.solver.kind = SolverSettings::Kind::kCholmod;
  s.dynamics.gravity_mps2 = g;
  SimulatorBuild b = buildSimulator(c, m, s);
  DynamicSimulator& sim = *b.simulator;
  auto& fem = dynamic_cast<CorotatedTetFem&>(sim.elements());
  fem.setCorotated(v.formulation != "linear");
  fem.setVolumeTerm(v.volume);
  SettleOptions o = s.settle;
  o.time_step_s = v.dt_s;
  o.increment_tolerance_m = v.increment_tolerance_m;
  o.max_steps = v.max_steps;
  RunResult r;
  const auto t0 = Clock::now();
  if (v.stiffening) {
    // As bench_speed_accuracy's corotated+stiffening (the main job), on this formulation.
    DynamicsParams p = sim.params();
    p.time_step_s = v.dt_s;
    sim.setParams(p);
    StiffeningSimulation stiff(sim, m.mesh);
    stiff.setGravity(g * v.load_scale);
    long calls = 0;
    while (stiff.stats().steps < v.max_steps && calls < 2L * v.max_steps) {
      ++calls;
      const StiffeningStepResult sr = stiff.step();
      if (sr.advanced && stiff.settled()) break;
    }
    r.steps = static_cast<int>(stiff.stats().steps);
    r.settled = stiff.settled();
    r.seconds = since(t0);
    r.u = sim.displacement();
    r.inverted = static_cast<int>(invertedTets(m.mesh.tets(), m.mesh.nodes() + r.u).size());
    return r;
  }
  for (int k = 1; k <= v.load_increments; ++k) {
    sim.setGravity(g * v.load_scale * k / v.load_increments);
    const int before = r.steps;
    const SettleResult sr = settle(sim, o, [&](int step, double) {
      const int inv = static_cast<int>(invertedTets(m.mesh.tets(), m.mesh.nodes() + sim.displacement()).size());
      if (inv > 0 && r.first_inverted_step < 0) r.first_inverted_step = before + step;
      r.max_inverted = std::max(r.max_inverted, inv);
    });
    r.steps += sr.steps;
    r.settled = r.settled && sr.settled;
  }
  r.seconds = since(t0);
  r.u = sim.displacement();
  r.inverted = static_cast<int>(invertedTets(m.mesh.tets(), m.mesh.nodes() + r.u).size());
  return r;
}

/// Per-element J = det F at displacement u: fraction below thresholds, minimum.
nlohmann::json jStats(const TetMesh& mesh, const Points& u, const char* label) {
  const Points x = mesh.nodes() + u;
  std::vector<double> J(mesh.numTets());
  for (int e = 0; e < mesh.numTets(); ++e) J[e] = deformationGradient(mesh, x, e).determinant();
  auto frac = [&](double t) {
    return static_cast<double>(std::count_if(J.begin(), J.end(), [t](double j) { return j < t; })) / J.size();
  };
  const double jmin = *std::min_element(J.begin(), J.end());
  double vol0 = 0, vol = 0;
  const Eigen::VectorXd v0 = mesh.tetVolumes();
  for (int e = 0; e < mesh.numTets(); ++e) vol0 += v0[e], vol += v0[e] * J[e];
  std::printf("  %-34s %7d tets | J<0.9 %6.2f%%  J<0.7 %6.2f%%  J<0.5 %6.2f%%  J<=0 %6.3f%% | min J %7.3f | dV %6.2f%%\n",
              label, mesh.numTets(), 100 * frac(0.9), 100 * frac(0.7), 100 * frac(0.5), 100 * frac(1e-300), jmin,
              100 * (vol / vol0 - 1));
  return {{"label", label},        {"elements", mesh.numTets()},     {"frac_J_below_0_9", frac(0.9)},
          {"frac_J_below_0_7", frac(0.7)}, {"frac_J_below_0_5", frac(0.5)}, {"frac_J_nonpositive", frac(1e-300)},
          {"min_J", jmin},         {"volume_change_percent", 100 * (vol / vol0 - 1)}};
}

}  // namespace

int main(int argc, char** argv) {
  std::string case_file = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml";
  std::string load_name = "supine", ref_element = "c3d4", json_path;
  int target = 5000, reference_target = 99390;
  bool quick = false;
  CalculixOptions copt;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw std::invalid_argument(k + " needs a value");
      return argv[++i];
    };
    if (k == "--case") case_file = value();
    else if (k == "--load") load_name = value();
    else if (k == "--target") target = std::stoi(value());
    else if (k == "--reference-target") reference_target = std::stoi(value());
    else if (k == "--reference-element") ref_element = value();
    else if (k == "--cache") copt.cache_dir = value();
    else if (k == "--json") json_path = value();
    else if (k == "--quick") quick = true;
    else {
      std::fprintf(stderr,
                   "usage: bench_corotated_inversion [--case FILE] [--load supine|hanging] [--target 5000]\n"
                   "         [--reference-target 99390] [--reference-element c3d4|c3d10] [--cache DIR] [--json FILE] [--quick]\n");
      return 2;
    }
  }
  const ModelCase base = loadModelCase(case_file);
  const SimulationSettings settings = loadSimulationSettings(case_file);
  const Eigen::Vector3d g = gravityLoad(base, gravityLoadCaseFromName(load_name), settings.gravity_mps2);
  ModelCase c = base;
  c.meshing.target_elements = target;
  bool from_cache = false;
  const SimulationModel m = cachedSimulationModel(c, copt.cache_dir, &from_cache);
  std::printf("case %s, load %s: g = (%.3f, %.3f, %.3f) m/s^2, E = %.0f Pa, nu = %.3f; mesh %d tets, %d nodes (%s)\n",
              base.name.c_str(), load_name.c_str(), g.x(), g.y(), g.z(), settings.material.youngs_modulus_pa,
              settings.material.poisson_ratio, m.mesh.numTets(), m.mesh.numNodes(), from_cache ? "cached" : "meshed");

  // The reference, if cached or computable.
  ModelCase rc = base;
  rc.meshing.target_elements = reference_target;
  const SimulationModel rm = cachedSimulationModel(rc, copt.cache_dir);
  const CalculixResult ref =
      solveWithCalculix(rm.mesh, referenceLoadCase(settings, rm.mesh, g, referenceElementFromName(ref_element)), copt);
  std::printf("reference: CalculiX %s neo-Hookean NLGEOM, %d tets, largest displacement %.3f mm (%s)\n\n",
              ref_element.c_str(), rm.mesh.numTets(), 1e3 * ref.displacement_m.rowwise().norm().maxCoeff(),
              ref.from_cache ? "cached" : "computed");
  Points lesions(static_cast<Eigen::Index>(base.lesions.size()), 3);
  for (std::size_t i = 0; i < base.lesions.size(); ++i) lesions.row(i) = base.lesions[i].position_m.transpose();

  using VT = CorotatedTetFem::VolumeTerm;
  std::vector<Variant> variants;
  variants.push_back({"corotated (baseline, dt 0.33 s)"});
  if (!quick) {
    variants.push_back({"linear FEM"});
    variants.back().formulation = "linear";
    variants.push_back({"corotated, dt 0.033 s"});
    variants.back().dt_s = 0.033;
    variants.back().max_steps = 3000;
    variants.push_back({"corotated, tight (dt 1 s, 1e-8 m)"});
    variants.back().dt_s = 1.0;
    variants.back().increment_tolerance_m = 1e-8;
    variants.push_back({"corotated, 20 load increments"});
    variants.back().load_increments = 20;
    variants.back().increment_tolerance_m = 1e-7;
    for (double sc : {0.25, 0.5, 0.75}) {
      variants.push_back({"corotated, load x" + std::to_string(sc).substr(0, 4)});
      variants.back().load_scale = sc;
    }
  }
  variants.push_back({"corotated, J-1 volume term"});
  variants.back().volume = VT::kDeterminant;
  variants.push_back({"corotated+stiffening (main job)"});
  variants.back().stiffening = true;
  variants.push_back({"corotated+stiffening, J-1 volume term"});
  variants.back().stiffening = true;
  variants.back().volume = VT::kDeterminant;
  if (!quick) {
    variants.push_back({"corotated, J-1 volume term, dt 0.033"});
    variants.back().volume = VT::kDeterminant;
    variants.back().dt_s = 0.033;
    variants.back().max_steps = 3000;
  }

  std::printf("%-40s | %6s %5s %6s %6s %4s | %8s %7s %7s %7s %7s\n", "run", "settle", "steps", "1stInv", "maxInv",
              "inv", "time[s]", "umax", "mean", "p95", "dV[%]");
  nlohmann::json out, rows = nlohmann::json::array();
  std::vector<RunResult> results;
  for (const Variant& v : variants) {
    const RunResult r = runVariant(c, m, settings, g, v);
    results.push_back(r);
    const double umax = 1e3 * r.u.rowwise().norm().maxCoeff();
    nlohmann::json row = {{"run", v.name},           {"dt_s", v.dt_s},
                          {"load_scale", v.load_scale}, {"load_increments", v.load_increments},
                          {"settled", r.settled},    {"steps", r.steps},
                          {"first_inverted_step", r.first_inverted_step}, {"max_inverted", r.max_inverted},
                          {"inverted", r.inverted},  {"seconds", r.seconds},
                          {"max_displacement_mm", umax}};
    if (v.load_scale == 1.0) {
      const DisplacementErrors e = compareDisplacements(m.mesh, r.u, rm.mesh, ref.displacement_m, lesions);
      std::printf("%-40s | %6s %5d %6d %6d %4d | %8.2f %7.3f %7.3f %7.3f %7.2f\n", v.name.c_str(), r.settled ? "yes" : "NO",
                  r.steps, r.first_inverted_step, r.max_inverted, r.inverted, r.seconds, umax, e.mean_mm, e.p95_mm,
                  e.volume_change_percent);
      row.update({{"error_mean_mm", e.mean_mm}, {"error_p95_mm", e.p95_mm}, {"volume_change_percent", e.volume_change_percent},
                  {"reference_volume_change_percent", e.reference_volume_change_percent}});
    } else {
      std::printf("%-40s | %6s %5d %6d %6d %4d | %8.2f %7.3f %7s %7s %7s\n", v.name.c_str(), r.settled ? "yes" : "NO",
                  r.steps, r.first_inverted_step, r.max_inverted, r.inverted, r.seconds, umax, "-", "-", "-");
    }
    {
      const std::vector<int> inv = invertedTets(m.mesh.tets(), m.mesh.nodes() + r.u);
      const std::vector<int>& cw = m.mesh.nodeSet("chest_wall");
      const std::vector<int>& sk = m.mesh.nodeSet("skin");
      const std::set<int> cws(cw.begin(), cw.end()), sks(sk.begin(), sk.end());
      int rim = 0;
      for (int e : inv) {
        bool c = false, k = false;
        for (int i = 0; i < 4; ++i) {
          c = c || cws.count(m.mesh.tets()(e, i));
          k = k || sks.count(m.mesh.tets()(e, i));
        }
        rim += c && k;
      }
      if (!inv.empty()) std::printf("%-40s   (%d of the %d inverted touch both the fixed chest wall and the skin)\n", "", rim,
                                    static_cast<int>(inv.size()));
      row["inverted_at_rim"] = rim;
    }
    std::fflush(stdout);
    rows.push_back(row);
  }
  out["runs"] = rows;

  // ---- the baseline's inverted and most compressed elements ----------------------------------------
  const Points x = m.mesh.nodes() + results[0].u;
  const std::vector<int> chest = m.mesh.hasNodeSet("chest_wall") ? m.mesh.nodeSet("chest_wall") : std::vector<int>{};
  const std::vector<int> skin = m.mesh.hasNodeSet("skin") ? m.mesh.nodeSet("skin") : std::vector<int>{};
  const std::set<int> chest_set(chest.begin(), chest.end()), skin_set(skin.begin(), skin.end());
  std::vector<std::pair<double, int>> byJ;
  for (int e = 0; e < m.mesh.numTets(); ++e) byJ.push_back({deformationGradient(m.mesh, x, e).determinant(), e});
  std::sort(byJ.begin(), byJ.end());
  const QualityStats q0 = qualityStats(m.mesh.tets(), m.mesh.nodes());
  std::printf("\nBaseline: the 15 elements of smallest J = det F (mesh: mean min dihedral %.1f deg, min %.1f deg)\n",
              q0.mean_min_dihedral_deg, q0.min_dihedral_deg);
  std::printf("%6s | %7s %7s | %6s %5s | %8s %8s | %24s | %8s | %9s\n", "elem", "J", "trS/3", "#chest", "#skin",
              "rest dih", "rest AR", "signed singular values", "rest mm", "|R-Rsvd|");
  nlohmann::json worst = nlohmann::json::array();
  int inv_touching_chest = 0, inv_touching_skin = 0, inv_total = 0;
  double max_rdiff = 0.0;
  for (int e = 0; e < m.mesh.numTets(); ++e) {
    const Eigen::Matrix3d F = deformationGradient(m.mesh, x, e);
    max_rdiff = std::max(max_rdiff, (rotationOf(F) - rotationOfBySvd(F)).norm());
  }
  for (std::size_t k = 0; k < byJ.size(); ++k) {
    const int e = byJ[k].second;
    int nc = 0, ns = 0;
    for (int i = 0; i < 4; ++i) {
      nc += chest_set.count(m.mesh.tets()(e, i)) ? 1 : 0;
      ns += skin_set.count(m.mesh.tets()(e, i)) ? 1 : 0;
    }
    if (byJ[k].first <= 0) {
      ++inv_total;
      inv_touching_chest += nc > 0;
      inv_touching_skin += ns > 0;
    }
    if (k >= 15) continue;
    const Eigen::Matrix3d F = deformationGradient(m.mesh, x, e);
    const Eigen::Matrix3d R = rotationOf(F);
    const Eigen::Matrix3d S = R.transpose() * F;
    Eigen::JacobiSVD<Eigen::Matrix3d> svd(F);
    Eigen::Vector3d sv = svd.singularValues();
    if (F.determinant() < 0) sv[2] = -sv[2];
    const auto& t = m.mesh.tets();
    const TetQuality tq = tetQuality(m.mesh.nodes().row(t(e, 0)), m.mesh.nodes().row(t(e, 1)), m.mesh.nodes().row(t(e, 2)),
                                     m.mesh.nodes().row(t(e, 3)));
    const double edge = 1e3 * std::cbrt(6 * std::sqrt(2.0) * std::abs(tq.volume_m3));
    const double rdiff = (R - rotationOfBySvd(F)).norm();
    std::printf("%6d | %7.3f %7.3f | %6d %5d | %8.1f %8.2f | %7.3f %7.3f %8.3f | %8.2f | %9.1e\n", e, byJ[k].first,
                S.trace() / 3, nc, ns, tq.min_dihedral_deg, tq.aspect_ratio, sv[0], sv[1], sv[2], edge, rdiff);
    worst.push_back({{"element", e},          {"J", byJ[k].first},  {"trS_over_3", S.trace() / 3},
                     {"chest_wall_nodes", nc}, {"skin_nodes", ns},   {"rest_min_dihedral_deg", tq.min_dihedral_deg},
                     {"rest_aspect_ratio", tq.aspect_ratio}, {"signed_singular_values", {sv[0], sv[1], sv[2]}},
                     {"rotation_vs_svd", rdiff}});
  }
  std::printf("inverted at the end: %d, of which touching the fixed chest wall %d, touching the skin %d; "
              "largest |rotationOf - rotationOfBySvd| over all elements %.1e\n",
              inv_total, inv_touching_chest, inv_touching_skin, max_rdiff);
  out["baseline_smallest_J"] = worst;
  out["baseline_inverted"] = {{"total", inv_total}, {"touching_chest_wall", inv_touching_chest},
                              {"touching_skin", inv_touching_skin}, {"max_rotation_vs_svd", max_rdiff}};

  // ---- J distributions --------------------------------------------------------------------------------
  std::printf("\nPer-element volume ratio J = det F at the settled state\n");
  nlohmann::json js = nlohmann::json::array();
  js.push_back(jStats(rm.mesh, ref.displacement_m, "CalculiX reference (its mesh)"));
  for (std::size_t i = 0; i < variants.size(); ++i)
    if (variants[i].load_scale == 1.0 && variants[i].load_increments == 1)
      js.push_back(jStats(m.mesh, results[i].u, variants[i].name.c_str()));
  out["J"] = js;
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << '\n';
  return 0;
}
