// breast_sim_run: builds the simulation model of a case (the software phantom or a label image), writes
// it for ParaView / 3D Slicer / CalculiX, then loads it with gravity of the supine position and runs
// the co-rotated FEM until it settles; writes the deformed mesh, the lesion positions and a summary.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>

#include <unistd.h>

#include <nlohmann/json.hpp>

#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/sliding/chest_wall_sliding.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"

namespace fs = std::filesystem;
using namespace breast_sim::core;

namespace {

const char* kUsage = R"(usage: breast_sim_run --case CASE.yaml --out DIR [--target-elements N] [--model-only]
                      [--solver multigrid|cholmod|jacobi-pcg] [--json FILE] [--quiet]

Builds the tetrahedral simulation model of a case, simulates gravity of the supine position on it
until it settles (the case's `simulation:` map, see config/phantom_default.yaml) and writes to DIR:
  model.vtu             prone mesh with region labels, node sets and element quality (ParaView, 3D Slicer)
  model.inp             the same mesh for CalculiX / Abaqus (C3D4, mm)
  supine_gravity.vtu    the settled deformed mesh: displacement_mm, von_mises_pa per element
  lesions.csv/.json     lesion positions, prone and after gravity [mm]
  model_summary.json    counts, timings, quality, volumes, and the simulation's statistics
  prone_labels.nrrd, prone_surface.obj, supine_target.obj   (phantom cases only)
Options:
  --case FILE            YAML case file (see config/phantom_default.yaml)
  --out DIR              output folder (created)
  --target-elements N    overrides meshing.target_elements of the case
  --model-only           build and write the model, do not simulate
  --solver NAME          overrides simulation.solver
  --json FILE            also write the summary to FILE
  --quiet                no progress bar
)";

struct Args {
  std::string case_file, out_dir, json, solver;
  int target_elements = 0;
  bool model_only = false, quiet = false;
};

Args parse(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw std::invalid_argument("option " + k + " needs a value\n" + kUsage);
      return argv[++i];
    };
    if (k == "--case") a.case_file = value();
    else if (k == "--out") a.out_dir = value();
    else if (k == "--json") a.json = value();
    else if (k == "--solver") a.solver = value();
    else if (k == "--model-only") a.model_only = true;
    else if (k == "--quiet") a.quiet = true;
    else if (k == "--target-elements") {
      const std::string v = value();
      try {
        a.target_elements = std::stoi(v);
      } catch (...) {
        throw std::invalid_argument("--target-elements '" + v + "' is not a whole number");
      }
      if (a.target_elements <= 0) throw std::invalid_argument("--target-elements must be positive, got " + v);
    } else if (k == "-h" || k == "--help") {
      std::cout << kUsage;
      std::exit(0);
    } else throw std::invalid_argument("unknown option '" + k + "'\n" + kUsage);
  }
  if (a.case_file.empty() || a.out_dir.empty()) throw std::invalid_argument(std::string("--case and --out are required\n") + kUsage);
  return a;
}

/// Gravity load of the supine position on the prone model [m/s²]: the prone shape already hangs under
/// prone gravity, so the load that takes it to supine is g_supine − g_prone (first-order unloading;
/// a gravity-free reference state is future work, as in the seed paper's section 5). The phantom
/// brings its own (tilted) supine gravity; an image case turns the prone direction around.
Eigen::Vector3d supineGravityLoad(const ModelCase& c, double g) {
  const Eigen::Vector3d prone = g * c.prone_gravity_direction.normalized();
  const Eigen::Vector3d supine = c.phantom ? c.phantom->gravity_supine_mps2 : Eigen::Vector3d(-prone);
  return supine - prone;
}

void progressBar(int step, int max_steps, double increment_m, double tolerance_m) {
  // In a log (not a terminal) one line every 10 steps instead of a redrawn bar.
  static const bool tty = isatty(fileno(stderr));
  if (!tty) {
    if (step % 10 == 0 || step == 1)
      std::fprintf(stderr, "  settling: step %d/%d, largest change %.4f mm\n", step, max_steps, increment_m * 1e3);
    return;
  }
  // Progress by the increment's approach to the tolerance on a log scale (steps alone say little).
  static double first = 0.0;
  if (step == 1) first = increment_m;
  double f = 0.0;
  if (first > tolerance_m && increment_m > 0)
    f = std::clamp(std::log(first / increment_m) / std::log(first / tolerance_m), 0.0, 1.0);
  const int width = 30, filled = static_cast<int>(f * width);
  std::fprintf(stderr, "\r  settling [%s%s] step %d/%d, largest change %.4f mm   ", std::string(filled, '#').c_str(),
               std::string(width - filled, ' ').c_str(), step, max_steps, increment_m * 1e3);
  std::fflush(stderr);
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const Args args = parse(argc, argv);
    const auto t0 = std::chrono::steady_clock::now();
    ModelCase c = loadModelCase(args.case_file);
    if (args.target_elements > 0) c.meshing.target_elements = args.target_elements;
    SimulationSettings settings = loadSimulationSettings(args.case_file);
    if (!args.solver.empty()) settings.solver.kind = SolverSettings::kindFromName(args.solver);
    const double t_case = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const SimulationModel m = buildSimulationModel(c);
    const double t_model = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

    fs::create_directories(args.out_dir);
    const fs::path out(args.out_dir);
    // Element quality as cell data, next to the region labels the writer adds.
    MeshFields fields;
    Eigen::MatrixXd aspect(m.mesh.numTets(), 1), dihedral(m.mesh.numTets(), 1), volume(m.mesh.numTets(), 1);
    for (int t = 0; t < m.mesh.numTets(); ++t) {
      const auto& x = m.mesh.nodes();
      const auto& T = m.mesh.tets();
      const TetQuality q = tetQuality(x.row(T(t, 0)), x.row(T(t, 1)), x.row(T(t, 2)), x.row(T(t, 3)));
      aspect(t, 0) = q.aspect_ratio;
      dihedral(t, 0) = q.min_dihedral_deg;
      volume(t, 0) = q.volume_m3 * 1e9;
    }
    fields.cell_data.push_back({"aspect_ratio", aspect});
    fields.cell_data.push_back({"min_dihedral_deg", dihedral});
    fields.cell_data.push_back({"volume_mm3", volume});
    writeTetMesh((out / "model.vtu").string(), m.mesh, fields);
    writeTetMesh((out / "model.inp").string(), m.mesh, {}, 1e-3);

    const double mesh_volume = m.mesh.volume();
    nlohmann::json s;
    s["case"] = c.name;
    s["elements"] = m.mesh.numTets();
    s["nodes"] = m.mesh.numNodes();
    s["node_sets"] = nlohmann::json::object();
    for (const auto& kv : m.mesh.nodeSets()) s["node_sets"][kv.first] = kv.second.size();
    s["boundary_faces"] = m.mesh.boundary().triangles.rows();
    s["prone_gravity_direction"] = {c.prone_gravity_direction.x(), c.prone_gravity_direction.y(), c.prone_gravity_direction.z()};
    s["boundary_closed"] = isClosedManifold(m.mesh.boundary().triangles);
    s["seconds"] = {{"case_and_image", t_case}, {"meshing", m.meshing.seconds}, {"model_total", t_model}};
    s["meshing"] = {{"passes", m.meshing.passes},
                    {"interior_size_mm", m.meshing.interior_size_m * 1e3},
                    {"skin_size_mm", m.meshing.skin_size_m * 1e3},
                    {"facet_distance_mm", m.meshing.facet_distance_m * 1e3},
                    {"chest_wall_faces", m.meshing.num_chest_wall_faces},
                    {"undecided_faces", m.meshing.num_undecided_faces},
                    {"components", m.meshing.num_components},
                    {"dropped_islands", m.meshing.dropped_components},
                    {"dropped_island_volume_mm3", m.meshing.dropped_volume_m3 * 1e9},
                    {"skin_faces", m.meshing.num_skin_faces}};
    s["quality"] = {{"inverted", m.quality.num_inverted},
                    {"min_dihedral_deg", m.quality.min_dihedral_deg},
                    {"mean_min_dihedral_deg", m.quality.mean_min_dihedral_deg},
                    {"max_aspect_ratio", m.quality.max_aspect_ratio},
                    {"mean_aspect_ratio", m.quality.mean_aspect_ratio},
                    {"dihedral_below_10deg", m.quality.num_dihedral_below_10deg}};
    s["volume_cm3"] = {{"mesh", mesh_volume * 1e6}, {"voxels", m.meshing.voxel_volume_m3 * 1e6}};
    if (c.phantom) {
      s["volume_cm3"]["analytic"] = c.phantom->prone_volume_m3 * 1e6;
      s["volume_cm3"]["supine_target_analytic"] = c.phantom->supine_volume_m3 * 1e6;
      writeLabelImage((out / "prone_labels.nrrd").string(), c.phantom->labels);
      writePhantomSurface((out / "prone_surface.obj").string(), c.phantom->prone_surface);
      writePhantomSurface((out / "supine_target.obj").string(), c.phantom->supine_surface);
    }

    // Gravity of the supine position, settled.
    Points lesions_after;
    SettleResult settled;
    if (!args.model_only) {
      const Eigen::Vector3d g_load = supineGravityLoad(c, settings.gravity_mps2);
      settings.dynamics.gravity_mps2 = g_load;
      const auto ts = std::chrono::steady_clock::now();
      SimulatorBuild b = buildSimulator(c, m, settings);  // fixes settings.fixed_node_set
      DynamicSimulator& sim = *b.simulator;
      const int max_steps = settings.settle.max_steps;
      const double tol = settings.settle.increment_tolerance_m;
      RunStats stiff_stats;
      SlidingStepStats sliding_stats;
      Points sliding_vectors;
      int sliding_steps = 0;
      bool sliding_settled = false, sliding_stalled = false;
      double sliding_seconds = 0.0;
      if (!settings.stiffening) {
        settled = settle(sim, settings.settle, [&](int step, double inc) {
          if (!args.quiet) progressBar(step, max_steps, inc, tol);
        });
      } else {
        // The seed's loop: moduli E_r = 1 + α s_VM, a step that inverts an element is repeated with
        // a larger α; settled by the static residual and speed (material/stiffening.h).
        DynamicsParams p = sim.params();
        if (settings.settle.time_step_s > 0) p.time_step_s = settings.settle.time_step_s;
        sim.setParams(p);
        StiffeningSimulation stiff(sim, m.mesh);
        stiff.setGravity(g_load);
        const auto tst = std::chrono::steady_clock::now();
        Eigen::VectorXd previous = sim.state().displacement_m;
        long calls = 0;
        while (stiff.stats().steps < max_steps && calls < 2L * max_steps) {
          ++calls;
          const StiffeningStepResult r = stiff.step();
          settled.last_increment_m = maxNodalNorm(sim.state().displacement_m - previous);
          previous = sim.state().displacement_m;
          if (!args.quiet) progressBar(static_cast<int>(stiff.stats().steps), max_steps, settled.last_increment_m, tol);
          if (r.advanced && stiff.stats().settled) break;
        }
        // Sliding on the chest wall (seed 2.4), after the fixed-wall settling: the wall nodes become
        // moving constraints, updated after every accepted step at the dynamics time step (the
        // explicit constraint update is tuned for it), until the wall stops moving and the tissue
        // has settled again.
        if (settings.sliding && !settings.fixed_node_set.empty()) {
          const auto tsl = std::chrono::steady_clock::now();
          ChestWallSliding sliding = ChestWallSliding::fromCase(c, m.mesh, SlidingSettings{});
          sliding.attach(sim);
          DynamicsParams pd = sim.params();
          pd.time_step_s = settings.dynamics.time_step_s;
          sim.setParams(pd);
          const long first = stiff.stats().steps;
          int quiet_steps = 0, sliding_stalls = 0;
          long sl_calls = 0;
          while (stiff.stats().steps - first < max_steps && sl_calls < 2L * max_steps) {
            ++sl_calls;
            const StiffeningStepResult r = stiff.step();
            if (!r.advanced) {
              // The last constraint move inverts elements that no α saves: take it back (hold the
              // wall nodes where they are) and stop sliding after three such steps in a row.
              Points hold(static_cast<Eigen::Index>(sliding.nodes().size()), 3);
              for (size_t i = 0; i < sliding.nodes().size(); ++i)
                hold.row(static_cast<Eigen::Index>(i)) = sim.state().displacement_m.segment<3>(3 * sliding.nodes()[i]).transpose();
              sim.setNodeTargets(sliding.nodes(), hold);
              if (++sliding_stalls >= 3) break;
              continue;
            }
            sliding_stalls = 0;
            const SlidingStepStats ss = sliding.update(sim, &sim.externalForces());
            sliding_stats = ss;
            settled.last_increment_m = maxNodalNorm(sim.state().displacement_m - previous);
            previous = sim.state().displacement_m;
            if (!args.quiet) progressBar(static_cast<int>(stiff.stats().steps - first), max_steps, settled.last_increment_m, tol);
            quiet_steps = ss.max_move_m <= tol && settled.last_increment_m <= tol ? quiet_steps + 1 : 0;
            if (quiet_steps >= 3) break;
          }
          sliding_steps = static_cast<int>(stiff.stats().steps - first);
          sliding_stalled = sliding_stalls >= 3;
          sliding_settled = quiet_steps >= 3;
          sliding_vectors = sliding.slidingVectors();
          sliding_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - tsl).count();
        }
        stiff_stats = stiff.stats();
        settled.settled = stiff_stats.settled && (!settings.sliding || sliding_settled);
        settled.steps = static_cast<int>(stiff_stats.steps);
        settled.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - tst).count();
        settled.max_displacement_m = stiff_stats.max_displacement_m;
      }
      if (!args.quiet && isatty(fileno(stderr))) std::fprintf(stderr, "\n");
      const double t_sim = std::chrono::duration<double>(std::chrono::steady_clock::now() - ts).count();
      const Points u = sim.displacement();
      const Points x = m.mesh.nodes() + u;
      lesions_after = m.lesion_embedding.positions(x);
      const QualityStats q = qualityStats(m.mesh.tets(), x);
      MeshFields df;
      df.point_data.push_back({"displacement_mm", u * 1e3});
      if (sliding_vectors.rows()) df.point_data.push_back({"sliding_mm", sliding_vectors * 1e3});
      sim.elasticForces();  // stresses at the settled state
      df.cell_data.push_back({"von_mises_pa", sim.elements().vonMisesStress()});
      df.cell_data.push_back({"modulus_factor", sim.elements().modulusFactors()});
      MeshWriteOptions wo;
      wo.vtk.positions_m = &x;
      writeTetMesh((out / "supine_gravity.vtu").string(), m.mesh, df, 1.0, wo);
      s["simulation"] = nlohmann::json::object();
      if (!settings.stiffening) {  // the stiffening driver keeps no solver statistics
        s["simulation"]["solver_iterations"] = settled.solver_iterations;
        s["simulation"]["unconverged_solves"] = settled.unconverged_solves;
      }
      s["simulation"].update({
          {"gravity_load_mps2", {g_load.x(), g_load.y(), g_load.z()}},
          {"solver", SolverSettings::kindName(settings.solver.kind)},
          {"multigrid_levels", b.multigrid_levels},
          {"youngs_modulus_pa", settings.material.youngs_modulus_pa},
          {"poisson_ratio", settings.material.poisson_ratio},
          {"settle_time_step_s", settings.settle.time_step_s > 0 ? settings.settle.time_step_s : settings.dynamics.time_step_s},
          {"stiffening", settings.stiffening},
          {"reversed_steps", stiff_stats.reversed_steps},
          {"reversal_fraction", stiff_stats.reversal_fraction},
          {"final_alpha_per_pa", stiff_stats.final_alpha_per_pa},
          {"max_modulus_factor", stiff_stats.max_modulus_factor},
          {"sliding", {{"on", settings.sliding && settings.stiffening},
                       {"steps", sliding_steps},
                       {"settled", sliding_settled},
                       {"stalled", sliding_stalled},
                       {"max_slide_mm", sliding_stats.max_slide_m * 1e3},
                       {"last_max_move_mm", sliding_stats.max_move_m * 1e3},
                       {"max_penetration_mm", sliding_stats.max_penetration_m * 1e3},
                       {"seconds", sliding_seconds}}},
          {"settled", settled.settled},
          {"steps", settled.steps},

          {"last_increment_mm", settled.last_increment_m * 1e3},
          {"max_displacement_mm", settled.max_displacement_m * 1e3},
          {"inverted_elements", q.num_inverted},
          {"volume_change_percent", 100.0 * (q.total_volume_m3 / mesh_volume - 1.0)},
          {"seconds", {{"setup", t_sim - settled.seconds}, {"steps", settled.seconds}}}});
      if (!settings.stiffening)
        s["simulation"]["seconds"].update({{"assembly", settled.assembly_seconds},
                                           {"solver_setup", settled.setup_seconds},
                                           {"solve", settled.solve_seconds}});
    }

    nlohmann::json lesions = nlohmann::json::array();
    std::ofstream csv(out / "lesions.csv");
    csv << "name,prone_x_mm,prone_y_mm,prone_z_mm,radius_mm,tet,outside_mm";
    if (lesions_after.rows()) csv << ",supine_gravity_x_mm,supine_gravity_y_mm,supine_gravity_z_mm,moved_mm";
    csv << '\n';
    for (size_t i = 0; i < m.lesions.size(); ++i) {
      const auto& l = m.lesions[i];
      const auto& e = m.lesion_embedding.points()[i];
      const Eigen::Vector3d p = l.position_m * 1e3;
      csv << l.name << ',' << p.x() << ',' << p.y() << ',' << p.z() << ',' << l.radius_m * 1e3 << ',' << e.tet << ','
          << e.outside_distance_m * 1e3;
      nlohmann::json j = {{"name", l.name}, {"prone_mm", {p.x(), p.y(), p.z()}}, {"radius_mm", l.radius_m * 1e3}, {"tet", e.tet}};
      if (lesions_after.rows()) {
        const Eigen::Vector3d q = lesions_after.row(static_cast<Eigen::Index>(i)).transpose() * 1e3;
        csv << ',' << q.x() << ',' << q.y() << ',' << q.z() << ',' << (q - p).norm();
        j["supine_gravity_mm"] = {q.x(), q.y(), q.z()};
        j["moved_mm"] = (q - p).norm();
      }
      csv << '\n';
      lesions.push_back(j);
    }
    std::ofstream(out / "lesions.json") << lesions.dump(2) << '\n';
    s["lesions"] = lesions;
    s["seconds"]["total"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::ofstream(out / "model_summary.json") << s.dump(2) << '\n';
    if (!args.json.empty()) std::ofstream(args.json) << s.dump(2) << '\n';

    std::printf("breast_sim run of case '%s'\n", c.name.c_str());
    std::printf("  %-28s %d tetrahedra, %d nodes (%s boundary)\n", "mesh", m.mesh.numTets(), m.mesh.numNodes(),
                s["boundary_closed"].get<bool>() ? "closed" : "OPEN");
    std::printf("  %-28s chest wall %zu, skin %zu nodes\n", "node sets",
                m.mesh.nodeSet(node_sets::kChestWall).size(), m.mesh.nodeSet(node_sets::kSkin).size());
    std::printf("  %-28s %.1f cm3 (voxels %.1f", "volume", mesh_volume * 1e6, m.meshing.voxel_volume_m3 * 1e6);
    if (c.phantom) std::printf(", analytic %.1f, error %+.2f%%", c.phantom->prone_volume_m3 * 1e6,
                               100.0 * (mesh_volume / c.phantom->prone_volume_m3 - 1.0));
    std::printf(")\n");
    std::printf("  %-28s %d inverted, min dihedral %.1f deg, max aspect ratio %.2f\n", "quality",
                m.quality.num_inverted, m.quality.min_dihedral_deg, m.quality.max_aspect_ratio);
    std::printf("  %-28s %.2f s (meshing %.2f s in %d pass(es))\n", "model time", t_model, m.meshing.seconds, m.meshing.passes);
    if (s.contains("simulation")) {
      const auto& j = s["simulation"];
      std::printf("  %-28s %s in %d steps (%.2f s, %s), max displacement %.2f mm\n", "supine gravity",
                  settled.settled ? "settled" : "NOT settled", settled.steps, settled.seconds,
                  j["solver"].get<std::string>().c_str(), settled.max_displacement_m * 1e3);
      std::printf("  %-28s %d inverted, volume change %+.2f%%\n", "deformed quality", j["inverted_elements"].get<int>(),
                  j["volume_change_percent"].get<double>());
      if (j["sliding"]["on"].get<bool>())
        std::printf("  %-28s %s after %d steps at dt %.3g s, largest slide %.2f mm, %.2f s\n", "chest-wall sliding",
                    j["sliding"]["settled"].get<bool>()   ? "stopped"
                    : j["sliding"]["stalled"].get<bool>() ? "STALLED (its moves invert elements)"
                                                          : "STILL MOVING",
                    j["sliding"]["steps"].get<int>(),
                    settings.dynamics.time_step_s, j["sliding"]["max_slide_mm"].get<double>(),
                    j["sliding"]["seconds"].get<double>());
      if (settings.stiffening)
        std::printf("  %-28s final alpha %.3g 1/Pa, largest E_r %.2f, %ld reversed steps (%.0f%%)\n", "von Mises stiffening",
                    j["final_alpha_per_pa"].get<double>(), j["max_modulus_factor"].get<double>(),
                    j["reversed_steps"].get<long>(), 100.0 * j["reversal_fraction"].get<double>());
    }
    for (const auto& l : lesions) {
      std::printf("  lesion %-21s prone (%.1f, %.1f, %.1f) mm", l["name"].get<std::string>().c_str(),
                  l["prone_mm"][0].get<double>(), l["prone_mm"][1].get<double>(), l["prone_mm"][2].get<double>());
      if (l.contains("supine_gravity_mm"))
        std::printf(" -> (%.1f, %.1f, %.1f) mm, moved %.1f mm", l["supine_gravity_mm"][0].get<double>(),
                    l["supine_gravity_mm"][1].get<double>(), l["supine_gravity_mm"][2].get<double>(), l["moved_mm"].get<double>());
      std::printf("\n");
    }
    std::printf("  %-28s %s\n", "written to", fs::absolute(out).string().c_str());
    return settled.settled || args.model_only ? 0 : 3;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "breast_sim_run: error: %s\n", e.what());
    return 2;
  }
}
