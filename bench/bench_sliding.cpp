// Sliding benchmark (seed Table 1, column "up./sl."), two parts per size:
//  1. cost per step: the phantom under the supine load (g_supine − g_prone) with von Mises
//     stiffening and time-step reversal, its chest-wall nodes sliding through
//     ChestWallSliding::afterStep() (the reaction forces come from the step's constraint rows, no
//     extra elastic-force evaluation): median stiffening call against median sliding update;
//  2. settling (--settle, on by default): the same combined loop until it settles — calls,
//     accepted and reversed steps, α at the end, inverted elements, largest slide, lateral slide of
//     the breast centres and the largest slide near the sternum, wall time. With --diagnose every
//     reversal is repeated once to classify the elements the trial step inverted (how many sliding
//     corners, rim, skin), which is how the cause of the inversions was found.
// Skin–wall contact (on by default, as in SlidingSettings): the settle line reports the contact
// nodes at the end, how many were made and released, and the smallest wall distance of the free
// skin at the end. --verbose N prints the loop every N calls.
// The one-off normal field and the set-up are reported too. Prints a table; --json FILE writes the
// same figures; --csv FILE writes the chest-wall nodes of the settled state (rest position, sliding
// vector, limiting weights) for docs/sliding/plot_sliding.py.
//   bench_sliding [--case FILE] [--targets 47895] [--steps 25] [--solver multigrid|cholmod]
//                 [--no-settle] [--max-calls 600] [--fixed-first] [--legacy] [--diagnose]
//                 [--rings N] [--move-smoothing N] [--min-volume F] [--no-rim] [--no-band]
//                 [--wall-distance-mm D] [--no-contact] [--contact-tol-mm T] [--contact-gap-mm G]
//                 [--no-release] [--release-pa P] [--max-slide-mm S] [--verbose N]
//                 [--sigma-fraction F] [--no-gaussian] [--json FILE] [--csv FILE]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include <omp.h>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/material/stiffening.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/sliding/chest_wall_sliding.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

struct Options {
  std::string case_path, json_path, csv_path, solver = "multigrid";
  std::vector<double> targets = {47895};
  int steps = 25, max_calls = 600, verbose = 0;
  bool settle = true, fixed_first = false, legacy = false, diagnose = false;
  SlidingSettings sliding;
};

int countInverted(const TetMesh& m, const Eigen::VectorXd& u, std::vector<int>* which = nullptr) {
  int c = 0;
  const Tets& t = m.tets();
  for (Eigen::Index e = 0; e < t.rows(); ++e) {
    Eigen::Vector3d p[4];
    for (int k = 0; k < 4; ++k) p[k] = m.nodes().row(t(e, k)).transpose() + u.segment<3>(3 * t(e, k));
    if ((p[1] - p[0]).dot((p[2] - p[0]).cross(p[3] - p[0])) <= 0) {
      ++c;
      if (which) which->push_back(static_cast<int>(e));
    }
  }
  return c;
}

// Lateral slide of the wall nodes near the breast centres (foot points), signed away from the
// sternum, and the largest slide of wall nodes within 30 mm of the sternum line (x = 0, two
// breasts) or of the medial rim (one breast: more than 40 mm medial of the centre) [mm].
struct SlideSummary {
  double centre_lateral_mm = 0, sternum_max_mm = 0, max_mm = 0;
};
SlideSummary summarize(const TetMesh& mesh, const ChestWallSliding& sl, const ModelCase& c) {
  SlideSummary s;
  const Points d = sl.slidingVectors();
  const auto& centres = sl.gaussianCentres();
  int nc = 0;
  for (int v : sl.nodes()) {
    const Eigen::Vector3d X = mesh.nodes().row(v).transpose();
    s.max_mm = std::max(s.max_mm, 1e3 * d.row(v).norm());
    for (const Eigen::Vector3d& ce : centres) {
      if ((X - ce).norm() < 15e-3) {
        const double lateral = ce.x() >= 0 ? 1.0 : -1.0;
        s.centre_lateral_mm += 1e3 * d(v, 0) * lateral;
        ++nc;
      }
    }
    const bool two = c.phantom && c.phantom->params.num_breasts == 2;
    bool sternum = false;
    if (two) sternum = std::abs(X.x()) < 30e-3;
    else if (!centres.empty()) {
      const double lateral = c.phantom && c.phantom->params.side == BreastSide::kRight ? -1.0 : 1.0;
      sternum = (X.x() - centres[0].x()) * lateral < -40e-3;
    }
    if (sternum) s.sternum_max_mm = std::max(s.sternum_max_mm, 1e3 * d.row(v).norm());
  }
  s.centre_lateral_mm /= std::max(1, nc);
  return s;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  o.case_path = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_two_breasts.yaml";
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--case") o.case_path = next();
    else if (a == "--targets") o.targets = parseList(next());
    else if (a == "--steps") o.steps = std::stoi(next());
    else if (a == "--solver") o.solver = next();
    else if (a == "--no-settle") o.settle = false;
    else if (a == "--max-calls") o.max_calls = std::stoi(next());
    else if (a == "--fixed-first") o.fixed_first = true;
    else if (a == "--legacy") o.legacy = true;
    else if (a == "--diagnose") o.diagnose = true;
    else if (a == "--rings") o.sliding.traction_smoothing_rings = std::stoi(next());
    else if (a == "--move-smoothing") o.sliding.move_smoothing_iterations = std::stoi(next());
    else if (a == "--min-volume") o.sliding.min_volume_fraction = std::stod(next());
    else if (a == "--no-rim") o.sliding.rim_follows_neighbours = false;
    else if (a == "--no-band") o.sliding.rim_band = false;
    else if (a == "--wall-distance-mm") o.sliding.max_wall_distance_m = 1e-3 * std::stod(next());
    else if (a == "--no-contact") o.sliding.contact = false;
    else if (a == "--contact-tol-mm") o.sliding.contact_tolerance_m = 1e-3 * std::stod(next());
    else if (a == "--contact-gap-mm") o.sliding.contact_gap_m = 1e-3 * std::stod(next());
    else if (a == "--no-release") o.sliding.contact_release = false;
    else if (a == "--release-pa") o.sliding.contact_release_pa = std::stod(next());
    else if (a == "--max-slide-mm") o.sliding.max_slide_m = 1e-3 * std::stod(next());
    else if (a == "--verbose") o.verbose = std::stoi(next());
    else if (a == "--sigma-fraction") o.sliding.gaussian_sigma_fraction = std::stod(next());
    else if (a == "--no-gaussian") o.sliding.gaussian_limit = false;
    else if (a == "--json") o.json_path = next();
    else if (a == "--csv") o.csv_path = next();
    else {
      std::fprintf(stderr,
                   "usage: bench_sliding [--case FILE] [--targets 47895,...] [--steps 25] [--solver multigrid|cholmod]\n"
                   "                     [--no-settle] [--max-calls 600] [--fixed-first] [--legacy] [--diagnose]\n"
                   "                     [--rings N] [--move-smoothing N] [--min-volume F] [--no-rim] [--no-band]\n"
                   "                     [--wall-distance-mm D] [--no-contact] [--contact-tol-mm T]\n"
                   "                     [--contact-gap-mm G] [--no-release] [--release-pa P] [--max-slide-mm S]\n"
                   "                     [--verbose N]\n"
                   "                     [--sigma-fraction 0.5] [--no-gaussian] [--json FILE] [--csv FILE]\n");
      return 2;
    }
  }
  const ModelCase base = loadModelCase(o.case_path);
  const SimulationSettings case_settings = loadSimulationSettings(o.case_path);
  std::printf("sliding benchmark: %s, %d threads%s%s\n", o.case_path.c_str(), omp_get_max_threads(),
              o.legacy ? ", LEGACY update()+hold" : "", o.fixed_first ? ", fixed-wall settle first" : "");
  std::printf("smoothing rings %d, move smoothing %d, min volume %.2f, rim follows %d, rim band %d, wall distance "
              "%.1f mm, Gaussian %d (sigma fraction %.2f), max slide %.1f mm\n",
              o.sliding.traction_smoothing_rings, o.sliding.move_smoothing_iterations, o.sliding.min_volume_fraction,
              o.sliding.rim_follows_neighbours, o.sliding.rim_band, 1e3 * o.sliding.max_wall_distance_m,
              o.sliding.gaussian_limit, o.sliding.gaussian_sigma_fraction, 1e3 * o.sliding.max_slide_m);
  std::printf("contact %d (tolerance %.2f mm, gap %.2f mm, release %d at %.0f Pa)\n", o.sliding.contact,
              1e3 * o.sliding.contact_tolerance_m, 1e3 * o.sliding.contact_gap_m, o.sliding.contact_release,
              o.sliding.contact_release_pa);
  nlohmann::json rows = nlohmann::json::array();
  for (double target : o.targets) {
    ModelCase c = base;
    c.meshing.target_elements = static_cast<int>(target);
    const SimulationModel model = buildSimulationModel(c);
    SimulationSettings ss = case_settings;
    ss.solver.kind = SolverSettings::kindFromName(o.solver);
    const Eigen::Vector3d g_prone = c.phantom ? c.phantom->gravity_prone_mps2
                                              : Eigen::Vector3d(9.81 * c.prone_gravity_direction.normalized());
    const Eigen::Vector3d g_supine = c.phantom ? c.phantom->gravity_supine_mps2 : Eigen::Vector3d(-g_prone);
    const Eigen::Vector3d g_load = g_supine - g_prone;
    ss.dynamics.gravity_mps2 = g_load;
    nlohmann::json row = {{"target_elements", static_cast<int>(target)},
                          {"tets", model.mesh.numTets()},
                          {"nodes", model.mesh.numNodes()}};

    auto t0 = Clock::now();
    auto surface = std::make_shared<const ChestWallSurface>(c.image, c.labels.chest_wall, o.sliding.field);
    const double field_s = since(t0);
    auto makeSliding = [&]() {
      return ChestWallSliding(model.mesh, model.mesh.nodeSet(node_sets::kChestWall), surface, o.sliding, &c.image,
                              c.labels, c.nipples_m, c.prone_gravity_direction);
    };
    row["normal_field_ms"] = 1e3 * field_s;

    // 1. Cost per step (from the rest state, dynamics time step).
    {
      SimulatorBuild b = buildSimulator(c, model, ss);
      DynamicSimulator& sim = *b.simulator;
      StiffeningSimulation stiff(sim, model.mesh);
      stiff.setGravity(g_load);
      t0 = Clock::now();
      ChestWallSliding sl = makeSliding();
      sl.attach(sim);
      const double setup_s = since(t0);
      std::vector<double> step_t, slide_t;
      SlidingStepStats last;
      for (int k = 0; k < o.steps; ++k) {
        t0 = Clock::now();
        const StiffeningStepResult r = stiff.step();
        step_t.push_back(since(t0));
        last = sl.afterStep(stiff, r);
        slide_t.push_back(last.seconds);
      }
      const double step_ms = 1e3 * median(step_t), sl_ms = 1e3 * median(slide_t);
      std::printf("\n%7s %6s %5s | %9s %9s | %10s %9s %7s | %8s\n", "tets", "nodes", "wall", "field[ms]", "setup[ms]",
                  "stiff[ms]", "slide[ms]", "sl/step", "slide_mm");
      std::printf("%7d %6d %5zu | %9.1f %9.1f | %10.2f %9.3f %6.1f%% | %8.2f   (median of %d calls)\n",
                  model.mesh.numTets(), model.mesh.numNodes(), sl.nodes().size(), 1e3 * field_s, 1e3 * setup_s, step_ms,
                  sl_ms, 100.0 * sl_ms / step_ms, 1e3 * last.max_slide_m, o.steps);
      row.update({{"wall_nodes", sl.nodes().size()},
                  {"held_nodes", sl.heldNodes()},
                  {"rim_nodes", std::count(sl.rimFlags().begin(), sl.rimFlags().end(), 1)},
                  {"sliding_setup_ms", 1e3 * setup_s},
                  {"cost_calls", o.steps},
                  {"stiffening_call_median_ms", step_ms},
                  {"sliding_update_median_ms", sl_ms}});
    }

    // 2. Settling: gravity + stiffening + sliding.
    if (o.settle) {
      SimulatorBuild b = buildSimulator(c, model, ss);
      DynamicSimulator& sim = *b.simulator;
      StiffeningSimulation stiff(sim, model.mesh);
      stiff.setGravity(g_load);
      const auto ts = Clock::now();
      if (o.fixed_first) {  // as the main job does: settle on the fixed wall with the long step first
        DynamicsParams p = sim.params();
        p.time_step_s = ss.settle.time_step_s;
        sim.setParams(p);
        for (int k = 0; k < 2 * ss.settle.max_steps; ++k) {
          const StiffeningStepResult r = stiff.step();
          if (r.advanced && stiff.settled()) break;
        }
        p.time_step_s = ss.dynamics.time_step_s;
        sim.setParams(p);
      }
      const RunStats before = stiff.stats();
      ChestWallSliding sl = makeSliding();
      sl.attach(sim);
      int calls = 0, take_backs = 0, held = 0, quiet = 0, stalls = 0, guard_limited = 0, contacts = 0;
      double min_skin_h = std::numeric_limits<double>::quiet_NaN();
      bool settled = false;
      double slide_s = 0, max_alpha = 0;
      std::map<std::string, int> classes;
      const std::vector<char> is_skin = [&] {
        std::vector<char> f(model.mesh.numNodes(), 0);
        for (int v : model.mesh.nodeSet(node_sets::kSkin)) f[v] = 1;
        return f;
      }();
      std::vector<char> is_wall(model.mesh.numNodes(), 0), is_rim(model.mesh.numNodes(), 0);
      for (size_t i = 0; i < sl.nodes().size(); ++i) {
        is_wall[sl.nodes()[i]] = 1;
        is_rim[sl.nodes()[i]] = sl.rimFlags()[i];
      }
      SimulationState pre;
      const double tol = ss.settle.increment_tolerance_m;
      while (calls < o.max_calls) {
        if (o.diagnose) pre = sim.state();
        const StiffeningStepResult r = stiff.step();
        ++calls;
        max_alpha = std::max(max_alpha, r.alpha_per_pa);
        if (o.diagnose && r.reversals > 0) {
          // Repeat the first trial from the start state (moduli of the end of the call) to see
          // which elements invert, then go back.
          const SimulationState post = sim.state();
          sim.restore(pre);
          sim.step();
          std::vector<int> inv;
          countInverted(model.mesh, sim.state().displacement_m, &inv);
          static int printed = 0;
          for (int e : inv) {
            if (printed < 12) {
              ++printed;
              std::printf("  call %d: element %d inverted; corners:", calls, e);
              auto vol = [&](const Eigen::VectorXd& u) {
                Eigen::Vector3d p[4];
                for (int k = 0; k < 4; ++k)
                  p[k] = model.mesh.nodes().row(model.mesh.tets()(e, k)).transpose() + u.segment<3>(3 * model.mesh.tets()(e, k));
                return (p[1] - p[0]).dot((p[2] - p[0]).cross(p[3] - p[0])) / 6.0;
              };
              for (int k = 0; k < 4; ++k) {
                const int v = model.mesh.tets()(e, k);
                const Eigen::Vector3d x = model.mesh.nodes().row(v).transpose() + sim.state().displacement_m.segment<3>(3 * v);
                const Eigen::Vector3d du = sim.state().displacement_m.segment<3>(3 * v) - pre.displacement_m.segment<3>(3 * v);
                std::printf(" [%s%s h=%.2fmm du=(%.2f,%.2f,%.2f)mm]", is_wall[v] ? (is_rim[v] ? "Wr" : "W") : "F",
                            is_skin[v] ? "s" : "", 1e3 * surface->signedDistance(x), 1e3 * du.x(), 1e3 * du.y(), 1e3 * du.z());
              }
              std::printf(" V rest %.3g, before %.3g, trial %.3g mm3, E_r %.3g\n",
                          1e9 * model.mesh.tetVolumes()[e], 1e9 * vol(pre.displacement_m),
                          1e9 * vol(sim.state().displacement_m), sim.elements().modulusFactors()[e]);
            }
            int w = 0, rim = 0, skin = 0;
            for (int k = 0; k < 4; ++k) {
              const int v = model.mesh.tets()(e, k);
              w += is_wall[v];
              rim += is_rim[v];
              skin += is_skin[v];
            }
            classes["wall" + std::to_string(w) + (rim ? "_rim" : "") + (skin ? "_skin" : "")]++;
          }
          sim.restore(post);
        }
        SlidingStepStats st;
        if (o.legacy) {
          // The main job's loop before afterStep(): update() after accepted steps, hold the wall
          // after a call that could not advance, give up after three in a row.
          if (!r.advanced) {
            Points hold(static_cast<Eigen::Index>(sl.nodes().size()), 3);
            for (size_t i = 0; i < sl.nodes().size(); ++i)
              hold.row(static_cast<Eigen::Index>(i)) = sim.state().displacement_m.segment<3>(3 * sl.nodes()[i]).transpose();
            sim.setNodeTargets(sl.nodes(), hold);
            ++take_backs;
            if (++stalls >= 3) break;
            continue;
          }
          stalls = 0;
          st = sl.update(sim, &sim.externalForces());
          slide_s += st.seconds + st.force_seconds;
        } else {
          st = sl.afterStep(stiff, r);
          slide_s += st.seconds;
          take_backs += st.taken_back ? 1 : 0;
          held += st.held_wall ? 1 : 0;
          contacts = st.contacts;
          if (r.advanced) min_skin_h = st.min_free_skin_distance_m;
        }
        if (o.verbose > 0 && calls % o.verbose == 0)
          std::printf("  call %d: %s, reversals %d, alpha %.3g /Pa, move %.4f mm (scale %.3g), slide %.2f mm, contacts %d "
                      "(+%d −%d), free skin h min %.2f mm, settled %d\n",
                      calls, r.advanced ? "advanced" : "NOT advanced", r.reversals, r.alpha_per_pa, 1e3 * st.max_move_m,
                      st.move_scale, 1e3 * st.max_slide_m, st.contacts, st.contacts_added, st.contacts_released,
                      1e3 * st.min_free_skin_distance_m, stiff.settled());
        guard_limited += st.guard_limited;
        quiet = r.advanced && stiff.settled() && st.max_move_m <= tol ? quiet + 1 : 0;
        if (quiet >= 3) {
          settled = true;
          break;
        }
      }
      const double wall_s = since(ts);
      const RunStats rs = stiff.stats();
      const int inverted = countInverted(model.mesh, sim.state().displacement_m);
      const SlideSummary sum = summarize(model.mesh, sl, c);
      const long acc = rs.steps - before.steps, rev = rs.reversed_steps - before.reversed_steps;
      const double frac = acc + rev > 0 ? static_cast<double>(rev) / static_cast<double>(acc + rev) : 0.0;
      std::printf("settle: %s after %d calls (%ld accepted, %ld reversed = %.1f %%, %d take-backs, %d holds), %.1f s "
                  "(sliding %.2f s)\n",
                  settled ? "settled" : "NOT settled", calls, acc, rev, 100 * frac, take_backs, held, wall_s, slide_s);
      std::printf("        alpha end %.3g /Pa (max %.3g, ceiling %.3g), inverted %d, max E_r %.3g, max displacement %.2f mm\n",
                  rs.final_alpha_per_pa, max_alpha, stiff.params().alpha.max_alpha_per_pa, inverted,
                  rs.max_modulus_factor, 1e3 * rs.max_displacement_m);
      std::printf("        slide: max %.2f mm, breast centres %.2f mm lateral, sternum region max %.2f mm; guard-limited "
                  "moves %d\n",
                  sum.max_mm, sum.centre_lateral_mm, sum.sternum_max_mm, guard_limited);
      std::printf("        contact: %d nodes at the end (%d made, %d released), free skin min wall distance %.2f mm\n",
                  contacts, sl.contactsMade(), sl.contactsReleased(), 1e3 * min_skin_h);
      if (o.diagnose) {
        std::printf("        inverted in reversed trials by class (wallK = K sliding corners):");
        for (const auto& kv : classes) std::printf(" %s:%d", kv.first.c_str(), kv.second);
        std::printf("\n");
      }
      nlohmann::json js = {{"settled", settled},
                           {"calls", calls},
                           {"accepted_steps", acc},
                           {"reversed_steps", rev},
                           {"reversal_fraction", frac},
                           {"take_backs", take_backs},
                           {"wall_holds", held},
                           {"seconds", wall_s},
                           {"sliding_seconds", slide_s},
                           {"final_alpha_per_pa", rs.final_alpha_per_pa},
                           {"max_alpha_per_pa", max_alpha},
                           {"alpha_ceiling_per_pa", stiff.params().alpha.max_alpha_per_pa},
                           {"inverted_elements", inverted},
                           {"max_modulus_factor", rs.max_modulus_factor},
                           {"max_displacement_mm", 1e3 * rs.max_displacement_m},
                           {"max_slide_mm", sum.max_mm},
                           {"centre_lateral_slide_mm", sum.centre_lateral_mm},
                           {"sternum_region_max_slide_mm", sum.sternum_max_mm},
                           {"guard_limited_moves", guard_limited},
                           {"contact", o.sliding.contact},
                           {"contact_nodes_end", contacts},
                           {"contacts_made", sl.contactsMade()},
                           {"contacts_released", sl.contactsReleased()},
                           {"free_skin_min_wall_distance_mm", std::isfinite(min_skin_h) ? 1e3 * min_skin_h : -1.0},
                           {"max_slide_setting_mm", 1e3 * o.sliding.max_slide_m},
                           {"gaussian_limit", o.sliding.gaussian_limit},
                           {"rim_band", o.sliding.rim_band},
                           {"fixed_wall_settle_first", o.fixed_first},
                           {"legacy", o.legacy}};
      if (o.diagnose) js["inverted_trial_classes"] = classes;
      row["settle"] = js;
      if (!o.csv_path.empty()) {
        std::ofstream f(o.csv_path);
        f << "node,x_mm,y_mm,z_mm,slide_x_mm,slide_y_mm,slide_z_mm,weight,gaussian,thickness_mm,contact\n";
        const Points d = sl.slidingVectors();
        std::vector<int> all = sl.nodes();
        const std::vector<int> cn = sl.contactNodes();
        all.insert(all.end(), cn.begin(), cn.end());
        for (size_t i = 0; i < all.size(); ++i) {
          const int v = all[i];
          f << v << ',' << 1e3 * model.mesh.nodes()(v, 0) << ',' << 1e3 * model.mesh.nodes()(v, 1) << ','
            << 1e3 * model.mesh.nodes()(v, 2) << ',' << 1e3 * d(v, 0) << ',' << 1e3 * d(v, 1) << ',' << 1e3 * d(v, 2)
            << ',' << sl.weights()[i] << ',' << sl.gaussianFactors()[i] << ',' << 1e3 * sl.tissueThickness()[i] << ','
            << (i >= sl.nodes().size() ? 1 : 0) << '\n';
        }
      }
    }
    rows.push_back(row);
  }
  std::printf("(stiff = one StiffeningSimulation::step() call; slide = ChestWallSliding::afterStep(), reactions from\n"
              " the constraint rows, no extra elastic-force evaluation)\n");
  if (!o.json_path.empty()) {
    nlohmann::json j = {{"case", o.case_path},
                        {"threads", omp_get_max_threads()},
                        {"solver", o.solver},
                        {"traction_smoothing_rings", o.sliding.traction_smoothing_rings},
                        {"move_smoothing_iterations", o.sliding.move_smoothing_iterations},
                        {"min_volume_fraction", o.sliding.min_volume_fraction},
                        {"rim_follows_neighbours", o.sliding.rim_follows_neighbours},
                        {"rim_band", o.sliding.rim_band},
                        {"contact", o.sliding.contact},
                        {"contact_tolerance_mm", 1e3 * o.sliding.contact_tolerance_m},
                        {"contact_gap_mm", 1e3 * o.sliding.contact_gap_m},
                        {"contact_release", o.sliding.contact_release},
                        {"contact_release_pa", o.sliding.contact_release_pa},
                        {"gaussian_limit", o.sliding.gaussian_limit},
                        {"max_slide_mm", 1e3 * o.sliding.max_slide_m},
                        {"rows", rows}};
    std::ofstream(o.json_path) << j.dump(2) << "\n";
  }
  return 0;
}
