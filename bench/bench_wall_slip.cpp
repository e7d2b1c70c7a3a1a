// bench_wall_slip: the cost of implicit sliding (sliding/wall_slip.h) per step beside the simulation
// step, at the seed's Table-1 size (the seed's update/sliding column is 35 ms at 47,895
// elements on 2012 hardware; target ≤ 2 ms). The phantom settles under supine gravity with the wall
// fixed, then the wall is released onto implicit sliding and `--steps` steps of the pipeline's loop
// run at the dynamics time step:
//   slip.beforeStep (springs from the state) → StiffeningSimulation::step() → slip.afterStep (friction).
// Per step: the sliding update (before + after), the whole stiffening call, and — from the same
// state, restored afterwards — one bare DynamicSimulator::step(); the stiffening call minus the bare
// step is the modulus update, inversion check and undo history. Medians over the steps.
//   bench_wall_slip [--case config/phantom_default.yaml] [--targets 47895,20000] [--steps 25] [--json FILE]
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/core/sliding/wall_slip.h"

using namespace breast_sim;
using namespace breast_sim::core;

int main(int argc, char** argv) {
  std::string case_path = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml", json_path;
  std::vector<double> targets = {47895};
  int steps = 25;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--case") case_path = bench::argValue(argc, argv, i);
    else if (a == "--targets") targets = bench::parseList(bench::argValue(argc, argv, i));
    else if (a == "--steps") steps = std::stoi(bench::argValue(argc, argv, i));
    else if (a == "--json") json_path = bench::argValue(argc, argv, i);
    else {
      std::fprintf(stderr, "usage: bench_wall_slip [--case FILE] [--targets 47895,...] [--steps N] [--json FILE]\n");
      return a == "--help" ? 0 : 2;
    }
  }
  nlohmann::json out;
  out["case"] = case_path;
  out["steps"] = steps;
  std::printf("implicit sliding cost per step (%s, %d steps after the fixed-wall settle; medians) [ms]\n", case_path.c_str(), steps);
  std::printf("%8s %7s %6s | %9s | %8s %8s %8s %6s | %9s %9s\n", "tets", "nodes", "wall", "setup", "slide", "stiff", "step",
              "iters", "modulus", "slide[mm]");
  for (double target : targets) {
    ModelCase c = loadModelCase(case_path);
    c.meshing.target_elements = static_cast<int>(target);
    const SimulationModel model = buildSimulationModel(c);
    const PipelineSettings ps = loadPipelineSettings(case_path);
    SimulationSettings ss = ps.simulation;
    ss.dynamics.gravity_mps2 = c.phantom ? Eigen::Vector3d(c.phantom->gravity_supine_mps2 - c.phantom->gravity_prone_mps2)
                                         : Eigen::Vector3d(-2.0 * ss.gravity_mps2 * c.prone_gravity_direction.normalized());
    SimulatorBuild b = buildSimulator(c, model, ss);
    DynamicSimulator& sim = *b.simulator;
    StiffeningSimulation stiff(sim, model.mesh, ps.stiffening);
    stiff.setGravity(ss.dynamics.gravity_mps2);
    DynamicsParams p = sim.params();
    p.time_step_s = ss.settle.time_step_s;
    sim.setParams(p);
    for (int k = 0; k < 2 * ss.settle.max_steps; ++k)
      if (stiff.step().advanced && stiff.settled()) break;
    p.time_step_s = ss.dynamics.time_step_s;
    sim.setParams(p);
    WallSlipSettings ws = ps.wall_slip;
    ws.static_friction = ps.sliding.static_friction;
    ws.kinetic_friction = ps.sliding.kinetic_friction;
    ws.static_threshold_pa = ps.sliding.static_threshold_pa;
    auto t0 = bench::Clock::now();
    WallSlip slip = WallSlip::fromCase(c, model.mesh, ps.sliding, ws);
    slip.attach(sim);
    const double setup_s = bench::since(t0);
    std::vector<double> slide_ms, stiff_ms, step_ms, iterations;
    WallSlipStats last;
    for (int k = 0; k < steps; ++k) {
      // A bare step from this state, for the comparison, then back.
      const SimulationState before = sim.state();
      slip.beforeStep(sim);
      t0 = bench::Clock::now();
      iterations.push_back(sim.step().solve.iterations);
      step_ms.push_back(1e3 * bench::since(t0));
      sim.restore(before);
      // The pipeline's loop.
      t0 = bench::Clock::now();
      slip.beforeStep(sim);
      double slide = bench::since(t0);
      t0 = bench::Clock::now();
      const StiffeningStepResult r = stiff.step();
      stiff_ms.push_back(1e3 * bench::since(t0));
      t0 = bench::Clock::now();
      if (r.advanced) last = slip.afterStep(sim);
      slide += bench::since(t0);
      slide_ms.push_back(1e3 * slide);
    }
    const double slide = bench::median(slide_ms), st = bench::median(stiff_ms), step = bench::median(step_ms);
    std::printf("%8d %7d %6zu | %9.1f | %8.3f %8.2f %8.2f %6.1f | %9.2f %9.2f\n", model.mesh.numTets(), model.mesh.numNodes(),
                slip.nodes().size(), 1e3 * setup_s, slide, st, step, bench::median(iterations), st - step, 1e3 * last.max_slide_m);
    out["rows"].push_back({{"tets", model.mesh.numTets()},
                           {"nodes", model.mesh.numNodes()},
                           {"wall_nodes", slip.nodes().size()},
                           {"setup_ms", 1e3 * setup_s},
                           {"slide_ms", slide},
                           {"stiffening_step_ms", st},
                           {"bare_step_ms", step},
                           {"pcg_iterations", bench::median(iterations)},
                           {"modulus_update_ms", st - step},
                           {"max_slide_mm", 1e3 * last.max_slide_m}});
  }
  std::printf("(slide = WallSlip::beforeStep + afterStep; stiff = StiffeningSimulation::step(); step = a bare\n"
              " DynamicSimulator::step() from the same state; modulus = stiff - step: moduli, inversion check, history;\n"
              " setup = the chest-wall field and node geometry, once)\n");
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  return 0;
}
