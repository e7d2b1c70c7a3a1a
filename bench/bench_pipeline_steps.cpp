// bench_pipeline_steps: how many steps each stage of the prone-to-supine pipeline (gravity, sliding,
// morphing; seed Figure 2) takes, and what the run ends at, for variants of the case file's settings
// on ONE mesh per size (meshing is not repeatable run to run, so variants must share the model).
// Step counts do not depend on the machine's load; the wall times are printed as ratios against the
// first variant of the same size, measured in the same run.
//
//   bench_pipeline_steps [--case config/phantom_default.yaml] [--elements 10000,20000]
//                        [--variant NAME:section.key=value,section.key=value ...] [--trace]
//                        [--ensemble TOL,TOL,...] [--json FILE]
//
// A variant overrides keys of the case file (any key of simulation:, stiffening:, sliding:, morphing:,
// with the file's units; alpha.KEY is kept as another name of stiffening.KEY), e.g.
// --variant base: --variant long:morphing.time_step_s=0.33,stiffening.decrease_factor=0.6.
// Without --variant one variant runs: the case as it is. --trace prints every accepted step
// (stage, increment, pulled-vertex mean / p95 distance, α, the node that moved most, the largest move
// off the wall, the 95th percentile of the wall nodes' moves, the volume change, the lesions [mm]). --stretch F: the target is the model's own
// skin stretched by F along y (reachable with the wall fixed; use with simulation.gravity_mps2=0).
// --ensemble 1e-2,8e-3,...: each variant runs once per PCG relative tolerance (simulation.
// solver_relative_tolerance); the wall's stick/slip makes the lesions depend on such small differences
// in the path, and the table of ensembles gives each variant's mean lesions, its members' spread about
// them, and the distance of its mean from the first variant's (which is then comparable to the spread).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include "bench_util.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;
namespace fs = std::filesystem;

namespace {

struct Variant {
  std::string name;
  std::string group;  // with --ensemble: the variant this run is a member of (else its own name)
  std::vector<std::pair<std::string, std::string>> overrides;  // "section.key" → YAML scalar text
};

Variant parseVariant(const std::string& text) {
  Variant v;
  const size_t colon = text.find(':');
  v.name = colon == std::string::npos ? text : text.substr(0, colon);
  const std::string rest = colon == std::string::npos ? "" : text.substr(colon + 1);
  std::stringstream ss(rest);
  for (std::string item; std::getline(ss, item, ',');) {
    if (item.empty()) continue;
    const size_t eq = item.find('=');
    if (eq == std::string::npos || item.find('.') == std::string::npos || item.find('.') > eq)
      throw std::invalid_argument("variant '" + text + "': '" + item + "' is not section.key=value");
    v.overrides.push_back({item.substr(0, eq), item.substr(eq + 1)});
  }
  return v;
}

/// The case file with the variant's keys replaced, written next to the case (relative paths in it
/// keep working); returns its path.
std::string variantFile(const std::string& case_file, const Variant& v) {
  YAML::Node root = YAML::LoadFile(case_file);
  for (const auto& [dotted, value] : v.overrides) {
    const size_t dot = dotted.find('.');
    std::string section = dotted.substr(0, dot);
    const std::string key = dotted.substr(dot + 1);
    if (section == "alpha") section = "stiffening";  // the older name of the map
    root[section][key] = YAML::Load(value);
  }
  const fs::path out = fs::path(case_file).parent_path() /
                       (".bench_pipeline_steps_" + std::to_string(::getpid()) + "_" + v.name + ".yaml");
  std::ofstream f(out);
  f << root << '\n';
  return out.string();
}

/// One run of an ensemble: its variant and where it put the lesions [m].
struct Member {
  std::string group;
  Points lesions;
  double seconds = 0;
  long solves = 0;
};

/// The ensembles' table: per variant, the mean lesion positions of its members, how far its members
/// lie from that mean (the spread the solver tolerance alone makes), and how far the mean lies from
/// the first variant's mean.
void printEnsemble(const std::vector<Member>& members, int target, int elements, nlohmann::json& out) {
  std::vector<std::string> groups;
  for (const Member& m : members)
    if (std::find(groups.begin(), groups.end(), m.group) == groups.end()) groups.push_back(m.group);
  std::printf("\nensembles at %d elements (one run per solver tolerance): lesion positions [mm]\n", elements);
  std::printf("%-14s %-8s %-8s %-9s %-12s %-14s %s\n", "variant", "members", "solves", "seconds", "spread [mm]",
              "from first [mm]", "mean lesion positions [mm]");
  Points first_mean;
  double first_spread = 0;
  for (const std::string& g : groups) {
    std::vector<const Member*> in;
    for (const Member& m : members)
      if (m.group == g) in.push_back(&m);
    Points mean = Points::Zero(in.front()->lesions.rows(), 3);
    double seconds = 0, solves = 0;
    for (const Member* m : in) mean += m->lesions, seconds += m->seconds, solves += static_cast<double>(m->solves);
    const double n = static_cast<double>(in.size());
    mean /= n;
    double spread = 0;  // largest distance of a member's lesion from the mean
    for (const Member* m : in)
      for (Eigen::Index i = 0; i < mean.rows(); ++i) spread = std::max(spread, (m->lesions.row(i) - mean.row(i)).norm());
    if (first_mean.size() == 0) first_mean = mean, first_spread = spread;
    double from_first = 0;
    for (Eigen::Index i = 0; i < mean.rows(); ++i) from_first = std::max(from_first, (mean.row(i) - first_mean.row(i)).norm());
    std::printf("%-14s %-8zu %-8.1f %-9.2f %-12.3f %-14.3f", g.c_str(), in.size(), solves / n, seconds / n, spread * 1e3,
                from_first * 1e3);
    nlohmann::json lesions = nlohmann::json::array();
    for (Eigen::Index i = 0; i < mean.rows(); ++i) {
      std::printf(" (%.2f %.2f %.2f)", mean(i, 0) * 1e3, mean(i, 1) * 1e3, mean(i, 2) * 1e3);
      lesions.push_back({mean(i, 0) * 1e3, mean(i, 1) * 1e3, mean(i, 2) * 1e3});
    }
    std::printf("\n");
    out.push_back({{"target_elements", target}, {"elements", elements}, {"variant", g}, {"members", in.size()},
                   {"mean_solves", solves / n}, {"mean_seconds", seconds / n}, {"spread_mm", spread * 1e3},
                   {"mean_from_first_mm", from_first * 1e3}, {"first_spread_mm", first_spread * 1e3},
                   {"mean_lesions_mm", lesions}});
  }
  std::printf("spread: the largest distance of a member's lesion from its variant's mean; from first: the largest "
              "distance of a lesion's mean from the first variant's\n");
}

}  // namespace

int main(int argc, char** argv) {
  std::string case_file = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml", json_path;
  std::vector<double> sizes = {10000, 20000};
  std::vector<Variant> variants;
  bool trace = false;
  std::vector<std::string> ensemble;  // solver tolerances: each variant runs once per value
  double stretch = 0;  // > 0: the target is the model's own skin stretched by this factor along y (a reachable target)
  try {
    for (int i = 1; i < argc; ++i) {
      const std::string a = argv[i];
      auto next = [&] { return argValue(argc, argv, i); };
      if (a == "--case") case_file = next();
      else if (a == "--elements") sizes = parseList(next());
      else if (a == "--variant") variants.push_back(parseVariant(next()));
      else if (a == "--trace") trace = true;
      else if (a == "--stretch") stretch = std::stod(next());
      else if (a == "--json") json_path = next();
      else if (a == "--ensemble") {
        std::stringstream ss(next());
        for (std::string item; std::getline(ss, item, ',');)
          if (!item.empty()) ensemble.push_back((parseList(item), item));  // parseList validates the number
      } else {
        std::fprintf(stderr, "usage: bench_pipeline_steps [--case FILE] [--elements LIST] [--variant NAME:sec.key=v,...]... "
                             "[--trace] [--stretch F] [--ensemble TOL,TOL,...] [--json FILE]\n");
        return 2;
      }
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_pipeline_steps: %s\n", e.what());
    return 2;
  }
  if (variants.empty()) variants.push_back({"case", "", {}});
  for (Variant& v : variants) v.group = v.name;
  if (!ensemble.empty()) {
    // Each variant once per solver tolerance: runs that differ only by the PCG's stopping point.
    std::vector<Variant> members;
    for (const Variant& v : variants)
      for (const std::string& tol : ensemble) {
        Variant m = v;
        m.name = v.name + "@" + tol;
        m.overrides.push_back({"simulation.solver_relative_tolerance", tol});
        members.push_back(m);
      }
    variants = members;
  }
  struct Profile {
    std::string variant;
    int elements = 0;
    StepTotals totals;
    double outside_seconds = -1;  // on the last model of a variant: the run's seconds outside step() [s]
  };
  std::vector<Profile> profiles;
  nlohmann::json rows = nlohmann::json::array(), ensemble_rows = nlohmann::json::array();
  for (double size : sizes) {
    ModelCase c = loadModelCase(case_file);
    c.meshing.target_elements = static_cast<int>(size);
    const SimulationModel m = buildSimulationModel(c);
    std::printf("\n%s, %d elements (one mesh for every variant)\n", c.name.c_str(), m.mesh.numTets());
    std::printf("%-14s %-12s %-14s %-14s %-9s %-11s %-11s %-11s %-8s %-4s %-9s %-8s %-8s\n", "variant", "gravity",
                "sliding", "morphing", "steps/solves", "skin mean", "skin p95", "pulled p95", "vol [%]", "inv", "lesion d",
                "seconds", "ratio");
    double base_seconds = -1;
    Points base_lesions;
    std::vector<Member> members;
    for (const Variant& v : variants) {
      const std::string file = variantFile(case_file, v);
      PipelineSettings s;
      try {
        s = loadPipelineSettings(file);
      } catch (const std::exception& e) {
        fs::remove(file);
        std::fprintf(stderr, "variant %s: %s\n", v.name.c_str(), e.what());
        return 2;
      }
      fs::remove(file);
      ProneToSupinePipeline pipe(c, m, s);
      if (stretch > 0) {
        TargetSurface t;
        t.vertices_m = m.mesh.nodes();
        t.vertices_m.col(1) *= stretch;
        t.triangles = skinTriangles(m.mesh, m.mesh.nodeSet(node_sets::kSkin));
        pipe.setTarget(t);
      }
      PipelineProgressFn progress;
      // The trace names the node that moved most in the step: on the chest wall (W), other skin (S) or
      // inside (I), and its rest y [mm] (the phantom.s wall is the plane y = 0).
      std::vector<char> kind(static_cast<size_t>(m.mesh.numNodes()), 'I');
      for (int n : m.mesh.nodeSet(node_sets::kSkin)) kind[static_cast<size_t>(n)] = 'S';
      for (int n : m.mesh.nodeSet(node_sets::kChestWall)) kind[static_cast<size_t>(n)] = 'W';
      Eigen::VectorXd previous;
      if (trace)
        progress = [&](const PipelineProgress& p) {
          const Eigen::VectorXd& u = pipe.simulator().state().displacement_m;
          if (previous.size() != u.size()) previous = Eigen::VectorXd::Zero(u.size());
          int worst = 0;
          double w2 = -1, off_wall2 = 0;  // largest move of any node, of a node off the wall
          std::vector<double> wall_moves;
          for (int n = 0; n < m.mesh.numNodes(); ++n) {
            const double d2 = (u.segment<3>(3 * n) - previous.segment<3>(3 * n)).squaredNorm();
            if (d2 > w2) w2 = d2, worst = n;
            if (kind[static_cast<size_t>(n)] == 'W') wall_moves.push_back(std::sqrt(d2));
            else off_wall2 = std::max(off_wall2, d2);
          }
          double wall_p95 = 0;
          if (!wall_moves.empty()) {
            const size_t k = std::min(wall_moves.size() - 1, static_cast<size_t>(std::ceil(0.95 * wall_moves.size())) - 1);
            std::nth_element(wall_moves.begin(), wall_moves.begin() + static_cast<std::ptrdiff_t>(k), wall_moves.end());
            wall_p95 = wall_moves[k];
          }
          previous = u;
          double volume = 0, max_u = 0;
          deformationMeasures(m.mesh, u, volume, max_u);
          const Points lesions = m.lesion_embedding.positions(m.mesh.nodes() + pipe.displacement());
          std::printf("  %-8s %4d  inc %8.4f mm  mean %7.3f p95 %7.3f mm  alpha %.3g  node %d %c rest y %.1f mm  off-wall %.4f "
                      "wall p95 %.4f mm  vol %.3f %%  lesions",
                      stageName(p.stage), p.step, p.increment_m * 1e3, p.surface_mean_m * 1e3, p.surface_p95_m * 1e3,
                      p.alpha_per_pa, worst, kind[static_cast<size_t>(worst)], m.mesh.nodes()(worst, 1) * 1e3,
                      std::sqrt(off_wall2) * 1e3, wall_p95 * 1e3, volume);
          for (Eigen::Index i = 0; i < lesions.rows(); ++i)
            std::printf(" %.3f %.3f %.3f", lesions(i, 0) * 1e3, lesions(i, 1) * 1e3, lesions(i, 2) * 1e3);
          std::printf("\n");
        };
      pipe.run(progress);
      const StageReport &g = pipe.gravityReport(), &sl = pipe.slidingReport(), &mo = pipe.morphingReport();
      const PipelineMetrics fm = pipe.metrics();
      const double seconds = g.seconds + sl.seconds + mo.seconds;
      if (base_seconds < 0) base_seconds = seconds;
      const Points lesions = pipe.lesionPositions();
      if (base_lesions.size() == 0) base_lesions = lesions;
      double lesion_diff = 0;
      for (Eigen::Index i = 0; i < lesions.rows(); ++i)
        lesion_diff = std::max(lesion_diff, (lesions.row(i) - base_lesions.row(i)).norm());
      auto stage = [](const StageReport& r) {
        char b[64];
        if (!r.ran) return std::string("-");
        if (r.shortened_steps > 0)
          std::snprintf(b, sizeof b, "%d(%ld,%lds)%s", r.steps, r.reversed_steps, r.shortened_steps, r.converged ? "" : r.stuck ? "S" : "X");
        else
          std::snprintf(b, sizeof b, "%d(%ld)%s", r.steps, r.reversed_steps, r.converged ? "" : r.stuck ? "S" : "X");
        if (r.coarse_elements > 0) return std::to_string(r.coarse_steps) + "(" + std::to_string(r.coarse_reversed_steps) + ")c+" + b;
        return std::string(b);
      };
      // With coarse_start the gravity and sliding stages ran on the coarse model, and so did the
      // morphing stage's first coarse_steps (their solves are cheaper; the seconds say by how much).
      const int total = g.steps + sl.steps + mo.coarse_steps + mo.steps;
      // Every trial step costs a solve: accepted, reverted, taken back by the divergence guard or
      // repeated with reversed wall nodes sticking. The simulators count them (both models').
      long solves = pipe.simulator().totals().steps;
      if (pipe.coarse()) solves += pipe.coarse()->simulator().totals().steps;
      std::printf("%-14s %-12s %-14s %-14s %-4d/%-4ld %-11.3f %-11.3f %-11.3f %-8.2f %-4d %-9.3f %-8.2f %-8.2f\n",
                  v.name.c_str(), stage(g).c_str(), stage(sl).c_str(), stage(mo).c_str(), total, solves,
                  fm.surface.model_to_target.mean_m * 1e3, fm.surface.model_to_target.p95_m * 1e3, mo.surface_p95_m * 1e3,
                  fm.volume_change_percent, fm.inverted_elements, lesion_diff * 1e3, seconds, seconds / base_seconds);
      members.push_back({v.group, lesions, seconds, solves});
      // Where the seconds went, per model the steps ran on: the simulator's step() calls (assembly,
      // solver set-up, solve) and the rest of the stages (stiffening, sliding, morphing, stop rules).
      nlohmann::json profile = nlohmann::json::array();
      double step_seconds = 0;
      const size_t profiles_before = profiles.size();
      for (const ProneToSupinePipeline* p : {pipe.coarse(), static_cast<const ProneToSupinePipeline*>(&pipe)}) {
        if (!p) continue;
        const StepTotals& t = p->simulator().totals();
        if (t.steps == 0) continue;
        step_seconds += t.total_seconds;
        const double per = 1e3 / static_cast<double>(t.steps);
        profiles.push_back(Profile{v.name, p->model().mesh.numTets(), t});
        profile.push_back({{"elements", p->model().mesh.numTets()},
                           {"solves", t.steps},
                           {"iterations_per_solve", static_cast<double>(t.iterations) / static_cast<double>(t.steps)},
                           {"assembly_ms_per_solve", t.assembly_seconds * per},
                           {"setup_ms_per_solve", t.setup_seconds * per},
                           {"solve_ms_per_solve", t.solve_seconds * per},
                           {"step_ms_per_solve", t.total_seconds * per},
                           {"step_seconds", t.total_seconds}});
      }
      if (profiles.size() > profiles_before) profiles.back().outside_seconds = seconds - step_seconds;
      std::fflush(stdout);
      nlohmann::json overrides = nlohmann::json::object();
      for (const auto& [k, val] : v.overrides) overrides[k] = val;
      auto stageJson = [](const StageReport& r) {
        return nlohmann::json{{"ran", r.ran},       {"converged", r.converged},           {"stuck", r.stuck},
                              {"steps", r.steps},   {"reversed", r.reversed_steps},       {"seconds", r.seconds},
                              {"shortened", r.shortened_steps},
                              {"alpha_per_pa", r.final_alpha_per_pa}, {"max_slide_mm", r.max_slide_m * 1e3},
                              {"elements", r.elements}, {"coarse_steps", r.coarse_steps},
                              {"coarse_reversed", r.coarse_reversed_steps}, {"coarse_elements", r.coarse_elements}};
      };
      rows.push_back({{"elements", m.mesh.numTets()},
                      {"variant", v.name},
                      {"overrides", overrides},
                      {"gravity", stageJson(g)},
                      {"sliding", stageJson(sl)},
                      {"morphing", stageJson(mo)},
                      {"total_steps", total},
                      {"total_solves", solves},
                      {"friction_repeats", sl.friction_repeats + mo.coarse_friction_repeats + mo.friction_repeats},
                      {"skin_to_target_mean_mm", fm.surface.model_to_target.mean_m * 1e3},
                      {"skin_to_target_p95_mm", fm.surface.model_to_target.p95_m * 1e3},
                      {"pulled_mean_mm", mo.surface_mean_m * 1e3},
                      {"pulled_p95_mm", mo.surface_p95_m * 1e3},
                      {"volume_change_percent", fm.volume_change_percent},
                      {"inverted", fm.inverted_elements},
                      {"lesion_shift_from_first_mm", lesion_diff * 1e3},
                      {"lesions_mm", [&] {
                         nlohmann::json l = nlohmann::json::array();
                         for (Eigen::Index i = 0; i < lesions.rows(); ++i)
                           l.push_back({lesions(i, 0) * 1e3, lesions(i, 1) * 1e3, lesions(i, 2) * 1e3});
                         return l;
                       }()},
                      {"seconds", seconds},
                      {"outside_steps_seconds", seconds - step_seconds},
                      {"profile", profile},
                      {"ratio_to_first", seconds / base_seconds}});
    }
    if (!ensemble.empty()) printEnsemble(members, static_cast<int>(size), m.mesh.numTets(), ensemble_rows);
  }
  std::printf("\nwhere the time went: the simulator's step() calls per model (ms per solve) and the stages' own work "
              "outside them (stiffening, sliding, morphing forces, stop rules; whole run [s])\n");
  std::printf("%-14s %-9s %-7s %-8s %-9s %-8s %-8s %-8s %-9s %-10s\n", "variant", "elements", "solves", "its/sol",
              "assembly", "setup", "solve", "step", "steps[s]", "outside[s]");
  for (const Profile& p : profiles) {
    const double per = 1e3 / static_cast<double>(p.totals.steps);
    std::printf("%-14s %-9d %-7ld %-8.1f %-9.2f %-8.2f %-8.2f %-8.2f %-9.2f ", p.variant.c_str(), p.elements,
                p.totals.steps, static_cast<double>(p.totals.iterations) / static_cast<double>(p.totals.steps),
                p.totals.assembly_seconds * per, p.totals.setup_seconds * per, p.totals.solve_seconds * per,
                p.totals.total_seconds * per, p.totals.total_seconds);
    if (p.outside_seconds >= 0) std::printf("%-10.2f", p.outside_seconds);
    std::printf("\n");
  }
  std::printf("\nsteps(reversed[,shortened s]), X = not converged, S = stuck; n(r)c+: first on the coarse model (coarse_start); skin mean/p95: all skin -> target [mm]; pulled p95: the "
              "morphing's vertices [mm]; lesion d: largest lesion position change from the first variant [mm]\n");
  if (!json_path.empty()) {
    if (ensemble.empty()) std::ofstream(json_path) << rows.dump(2) << '\n';
    else std::ofstream(json_path) << nlohmann::json{{"runs", rows}, {"ensembles", ensemble_rows}}.dump(2) << '\n';
  }
  return 0;
}
