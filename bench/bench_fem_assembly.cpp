// Co-rotated FEM assembly benchmark: per-step cost of the element rotations, the elastic forces and
// the stiffness assembly, on phantom meshes of the seed paper's Table-1 sizes, for both volume terms
// (trace: tr S − 3, determinant: J − 1, the pipeline's default), and the whole assembly of a
// DynamicSimulator step (update + stiffness + mass diagonal, right-hand side and the elimination of
// the constrained DOFs: chest wall fixed, nipple targets) with a solver that does nothing, so the pose
// stays the same every step.
//   update     = rotations + forces: CorotatedTetFem::update() (F, polar rotation, stress, forces,
//                the per-node gather of the forces)
//   upd port.  = update() with the portable element kernel (setSimdKernels(false): SSE2, two lanes
//                per vector), timed in the same repetitions at a third pose; the same as update where
//                the processor lacks AVX-512 (CorotatedTetFem::updateHasSimd)
//   forces     = update() with setCorotated(false) (identity rotations, trace term): the same work
//                without the polar decomposition, so rotations ≈ update(trace) − forces
//   stiffness  = zeroing A + addStiffness()
//   assign     = assignStiffness(): the same A in one pass (rows cleared as the gather reaches them)
//   scalar     = assignStiffness() with the portable scalar gather (setSimdKernels(false)), timed in
//                the same repetitions; the same as assign where the processor lacks AVX-512VL
//   step asm   = DynamicSimulator::step()'s assembly_seconds; overhead = step asm − update − stiffness
// Figures are medians over the repetitions (the minima go to the JSON too): on a shared machine an
// OpenMP region whose second thread is descheduled waits for it, so single runs scatter widely.
// Prints a table; --json FILE writes the same figures. The linear solve is measured by bench_solvers.
// --clock cpu times the FEM calls by the process's CPU time instead of the wall clock: with one
// thread (OMP_NUM_THREADS=1) that is immune to the process being descheduled, for A/B comparisons
// on a loaded machine (step asm stays wall time).
//   bench_fem_assembly [--targets 47895,99390,...] [--reps 25] [--clock wall|cpu] [--json FILE]
#include <algorithm>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include <omp.h>

#include "bench_util.h"
#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/model/model_case.h"

using namespace breast_sim::core;
using breast_sim::bench::Clock;
using breast_sim::bench::median;

namespace {
/// Leaves the velocity at zero: every step re-assembles the same pose.
class NullSolver : public LinearSolver {
 public:
  void analyzePattern(const SparseMatrix&) override {}
  void factorize(const SparseMatrix&) override {}
  SolveStats solve(const Eigen::VectorXd& b, Eigen::VectorXd& x) override {
    x.setZero(b.size());
    return {0, 0.0, true, 0.0};
  }
  std::string name() const override { return "null"; }
};

double minimum(const std::vector<double>& v) { return v.empty() ? 0.0 : *std::min_element(v.begin(), v.end()); }

/// Seconds on the wall clock, or of the process's CPU time with `cpu`.
double now(bool cpu) {
  if (!cpu) return std::chrono::duration<double>(Clock::now().time_since_epoch()).count();
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

/// Milliseconds: median and minimum of repeated runs.
struct Timing {
  std::vector<double> s;
  double med() const { return 1e3 * median(s); }
  double min() const { return 1e3 * minimum(s); }
};
}  // namespace

int main(int argc, char** argv) {
  std::vector<int> targets = {47895, 99390, 158340, 313335};
  int reps = 25;
  std::string json_path;
  bool cpu_clock = false;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string k = argv[i], v = argv[i + 1];
    if (k == "--targets") {
      targets.clear();
      for (double t : breast_sim::bench::parseList(v)) targets.push_back(static_cast<int>(t));
    } else if (k == "--reps") reps = std::stoi(v);
    else if (k == "--json") json_path = v;
    else if (k == "--clock" && (v == "wall" || v == "cpu")) cpu_clock = v == "cpu";
    else {
      std::fprintf(stderr, "usage: bench_fem_assembly [--targets N,...] [--reps R] [--clock wall|cpu] [--json FILE]\n");
      return 2;
    }
  }
  const ModelCase base = loadModelCase(std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml");
  std::printf("threads %d, %d repetitions per size, medians [ms], %s time\n", omp_get_max_threads(), reps,
              cpu_clock ? "process CPU" : "wall");
  std::printf("AVX-512VL stiffness gather: %s; AVX-512 element update: %s\n",
              CorotatedTetFem::gatherHasSimd() ? "yes" : "no (assign = scalar)",
              CorotatedTetFem::updateHasSimd() ? "yes" : "no (update = upd port.)");
  std::printf("%8s %7s %6s %9s %9s %9s %9s %9s %9s %9s %9s %9s %9s\n", "tets", "nodes", "volume", "rotations", "forces",
              "update", "upd port.", "stiffness", "assign", "scalar", "sum", "step asm", "overhead");
  nlohmann::json rows = nlohmann::json::array();
  for (int target : targets) {
    ModelCase c = base;
    c.meshing.target_elements = target;
    const SimulationModel model = buildSimulationModel(c);
    // A deformed pose (sag under gravity-like shear) so rotations are not trivial, and a second one
    // a nanometre beside it: the repetitions alternate between the two, since an update at the
    // positions of the last one reuses its results (CorotatedTetFem::update) and would time nothing.
    Points x = model.mesh.nodes();
    for (int n = 0; n < x.rows(); ++n) x(n, 0) += 0.05 * x(n, 1) * x(n, 1);
    Points x_other = x, x_portable = x;
    x_other(0, 0) += 1e-9;
    x_portable(0, 0) += 2e-9;
    auto pose = [&](int r) -> const Points& { return r % 2 ? x : x_other; };  // the warm-ups are at x
    Eigen::VectorXd f;
    // Forces alone: identity rotations.
    Timing t_forces;
    {
      CorotatedTetFem plain(model.mesh, ElasticMaterial{});
      plain.setCorotated(false);
      plain.update(x, f);  // warm-up
      for (int r = 0; r < reps; ++r) {
        const double t0 = now(cpu_clock);
        plain.update(pose(r), f);
        t_forces.s.push_back(now(cpu_clock) - t0);
      }
    }
    for (const auto volume : {CorotatedTetFem::VolumeTerm::kTrace, CorotatedTetFem::VolumeTerm::kDeterminant}) {
      const char* volume_name = volume == CorotatedTetFem::VolumeTerm::kTrace ? "trace" : "det";
      CorotatedTetFem fem(model.mesh, ElasticMaterial{});
      fem.setVolumeTerm(volume);
      SparseMatrix A = fem.pattern().matrix();
      fem.update(x, f);  // warm-up
      Timing t_update, t_portable, t_assemble, t_assign, t_scalar, t_step;
      for (int r = 0; r < reps; ++r) {
        const double t0 = now(cpu_clock);
        fem.update(pose(r), f);
        const double t1 = now(cpu_clock);
        std::fill(A.valuePtr(), A.valuePtr() + A.nonZeros(), 0.0);
        fem.addStiffness(1.0, A);
        const double t2 = now(cpu_clock);
        fem.assignStiffness(1.0, A);
        const double t3 = now(cpu_clock);
        fem.setSimdKernels(false);
        fem.assignStiffness(1.0, A);
        const double t4 = now(cpu_clock);
        fem.update(x_portable, f);  // never the pose of the update before
        const double t5 = now(cpu_clock);
        fem.setSimdKernels(true);
        t_update.s.push_back(t1 - t0);
        t_assemble.s.push_back(t2 - t1);
        t_assign.s.push_back(t3 - t2);
        t_scalar.s.push_back(t4 - t3);
        t_portable.s.push_back(t5 - t4);
      }
      // The same pose through DynamicSimulator::step().
      DynamicsParams params;
      params.gravity_mps2 = {0, -9.81, 0};
      auto elements = std::make_unique<CorotatedTetFem>(model.mesh, ElasticMaterial{});
      elements->setVolumeTerm(volume);
      DynamicSimulator sim(model.mesh, std::move(elements), ElasticMaterial{}, params, std::make_unique<NullSolver>());
      sim.fixNodes(model.mesh.nodeSet("chest_wall"));
      if (model.mesh.nodeSets().count("nipple")) {
        const auto& nip = model.mesh.nodeSet("nipple");
        sim.setNodeTargets(nip, Points::Constant(static_cast<Eigen::Index>(nip.size()), 3, 1e-3));
      }
      SimulationState s0 = sim.state(), s1;
      for (int n = 0; n < x.rows(); ++n)
        s0.displacement_m.segment<3>(3 * n) = (x.row(n) - model.mesh.nodes().row(n)).transpose();
      s1 = s0;
      s1.displacement_m[0] += 1e-9;
      sim.restore(s0);
      sim.step();  // warm-up
      for (int r = 0; r < reps; ++r) {
        sim.restore(r % 2 ? s0 : s1);  // never the pose of the step before
        t_step.s.push_back(sim.step().assembly_seconds);
      }
      const double u = t_update.med(), a = t_assemble.med(), s = t_step.med(), fo = t_forces.med();
      const bool trace = volume == CorotatedTetFem::VolumeTerm::kTrace;
      std::printf("%8d %7d %6s %9.2f %9.2f %9.2f %9.2f %9.2f %9.2f %9.2f %9.2f %9.2f %9.2f\n", model.mesh.numTets(),
                  model.mesh.numNodes(), volume_name, u - fo, fo, u, t_portable.med(), a, t_assign.med(), t_scalar.med(),
                  u + a, s, s - u - a);
      std::fflush(stdout);
      rows.push_back({{"tets", model.mesh.numTets()},
                      {"nodes", model.mesh.numNodes()},
                      {"volume_term", trace ? "trace" : "determinant"},
                      {"rotations_ms_median", u - fo},
                      {"forces_ms_median", fo},
                      {"update_ms_median", u},
                      {"update_portable_ms_median", t_portable.med()},
                      {"stiffness_ms_median", a},
                      {"assign_stiffness_ms_median", t_assign.med()},
                      {"assign_stiffness_scalar_ms_median", t_scalar.med()},
                      {"step_assembly_ms_median", s},
                      {"step_overhead_ms_median", s - u - a},
                      {"forces_ms_min", t_forces.min()},
                      {"update_ms_min", t_update.min()},
                      {"update_portable_ms_min", t_portable.min()},
                      {"stiffness_ms_min", t_assemble.min()},
                      {"assign_stiffness_ms_min", t_assign.min()},
                      {"assign_stiffness_scalar_ms_min", t_scalar.min()},
                      {"step_assembly_ms_min", t_step.min()}});
    }
  }
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"benchmark", "fem_assembly"}, {"threads", omp_get_max_threads()},
                                               {"statistic", "median"},
                                               {"clock", cpu_clock ? "process_cpu" : "wall"}, {"rows", rows}}.dump(2) << '\n';
  return 0;
}
