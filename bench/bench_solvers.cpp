// Linear-solver benchmark: analyzePattern, factorize and solve of CHOLMOD, Jacobi-PCG and
// multigrid-PCG on the system of one implicit step of linear elasticity of the phantom
// (A = M/dt² + K at rest, E = 2 kPa, ν = 0.48, ρ = 1000 kg/m³, dt = 0.033 s, chest wall fixed),
// with ratios against Jacobi-PCG of the same run. Prints a table; --json FILE writes the same figures.
//   bench_solvers [--case FILE] [--targets 47895,...] [--tol 1e-8] [--repeats 7] [--max-coarsest 300]
//                 [--size-factor 2] [--variants cholmod,pcg-jacobi,mg:gs1,mg:jacobi1,mg:jacobi1/4,mg:cheb2,...]
//                 [--damping 0.6] [--morton] [--rotate DEG] [--step-tol 1e-2] [--poisson 0.48] [--json FILE]
// Variants "mg:<gs|jacobi|cheb><sweeps>[/<interval>][:ratio=R][:bound=B][:safety=S]": multigrid-PCG
// with that smoother and sweeps (Chebyshev: polynomial degree) before and after the coarse correction,
// coarse operators recomputed every <interval> factorizations; R = MultigridOptions::chebyshev_ratio,
// B = fine_eigenvalue_bound (0: power iteration on the fine level too), S = chebyshev_eigenvalue_safety.
// (The vertex-star Schwarz and coarse-degree prototypes are not in the tree; their measured rows are in
// docs/benchmarks/multigrid_chebyshev.md.)
// "sa[:theta=T][:nu=S][:coarse=N][:unsmoothed]": smoothed-aggregation multigrid-PCG
// (solver/aggregation_multigrid.h) with strength threshold T, S block-Jacobi sweeps, at most N coarsest
// DOFs; it gives two rows: "full" redoes the whole set-up in every factorize, "keep P" keeps the
// aggregates and prolongators of the first factorize and recomputes only the Galerkin products.
// Every solver factorizes the rest matrix A first ("first" column); the timed repeats then factorize
// the step matrix: A itself, or with --rotate DEG the co-rotated matrix of a bent breast (element
// rotations up to DEG about the chest-wall's z axis growing with the distance from the wall, moduli
// E_r from 1 at the wall to 3 at the front), so that "keep P" is measured on a changed matrix.
// "it 1e-2" is a cold solve to --step-tol; "V-cycle" the preconditioner's time per application.
// The CPU-time table (process CPU time, all threads) is the more robust figure on a shared machine
// when run with OMP_NUM_THREADS=1. "cold" solves start from x = 0; "warm" ones from the previous solution for a load changed by 1 %
// (what a time step sees). Times are medians of the repeats (the machine is shared); "factorize" of an
// interval variant is the mean (amortized). --morton renumbers the fine mesh along a Morton curve
// first, to show what the mesher's node order costs.
#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <memory>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include <omp.h>
#include <time.h>

#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "bench_util.h"
#include "../test/core/reference_step_matrix.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/solver/aggregation_multigrid.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "breast_sim/core/solver/multigrid.h"
#include "breast_sim/core/solver/pcg_solver.h"

using namespace breast_sim::core;
using namespace breast_sim::bench;

namespace {

// A = M/dt² + K of linear tetrahedra (lumped mass), 3×3-block layout, Dirichlet rows and
// columns of the fixed nodes zeroed with a unit diagonal. (The project's assembly is fem/.) At rest, or
// co-rotated: element stiffness E_r R K_e Rᵀ with R the rotation of the element's deformation gradient
// at the `deformed` positions [m] (polar decomposition by SVD) and E_r = modulus[e].
SparseMatrix implicitStepMatrix(const TetMesh& mesh, const std::vector<int>& fixed_nodes, double E_pa, double nu,
                                double density, double dt, const Points* deformed = nullptr,
                                const std::vector<double>* modulus = nullptr) {
  auto rotation = [&](int e) -> Eigen::Matrix3d {
    if (!deformed) return Eigen::Matrix3d::Identity();
    Eigen::Matrix3d Dm, Ds;
    for (int k = 0; k < 3; ++k) {
      Dm.col(k) = (mesh.nodes().row(mesh.tets()(e, k + 1)) - mesh.nodes().row(mesh.tets()(e, 0))).transpose();
      Ds.col(k) = (deformed->row(mesh.tets()(e, k + 1)) - deformed->row(mesh.tets()(e, 0))).transpose();
    }
    const Eigen::JacobiSVD<Eigen::Matrix3d> svd(Ds * Dm.inverse(), Eigen::ComputeFullU | Eigen::ComputeFullV);
    Eigen::Matrix3d U = svd.matrixU();
    if ((U * svd.matrixV().transpose()).determinant() < 0) U.col(2) *= -1.0;
    return U * svd.matrixV().transpose();
  };
  return breast_sim::test_support::stepMatrix(
      mesh, fixed_nodes, rotation, [&](int e) { return modulus ? (*modulus)[e] : 1.0; }, E_pa, nu, density, dt);
}

// A bent breast: node x rotated by θ(y) = θ_max · (−y / depth) about the z axis through (x_c, 0) (the
// chest wall is y = 0, the breast protrudes to −y), and per-element moduli E_r = 1 + 2 (−y_e / depth).
Points bentPositions(const TetMesh& mesh, double theta_max_deg, std::vector<double>& modulus) {
  const Points& x = mesh.nodes();
  const double depth = std::max(-x.col(1).minCoeff(), 1e-9), xc = x.col(0).mean();
  Points out = x;
  for (Eigen::Index i = 0; i < x.rows(); ++i) {
    const double t = theta_max_deg * M_PI / 180.0 * std::max(0.0, -x(i, 1) / depth);
    const double dx = x(i, 0) - xc, dy = x(i, 1);
    out(i, 0) = xc + std::cos(t) * dx - std::sin(t) * dy;
    out(i, 1) = std::sin(t) * dx + std::cos(t) * dy;
  }
  modulus.assign(static_cast<size_t>(mesh.numTets()), 1.0);
  for (int e = 0; e < mesh.numTets(); ++e) {
    double y = 0.0;
    for (int a = 0; a < 4; ++a) y += x(mesh.tets()(e, a), 1) / 4.0;
    modulus[e] = 1.0 + 2.0 * std::max(0.0, -y / depth);
  }
  return out;
}

// Gravity on the lumped masses plus a random part; 0 on fixed DOFs [N].
Eigen::VectorXd load(const TetMesh& mesh, const std::vector<int>& fixed_nodes, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Eigen::VectorXd b = Eigen::VectorXd::Zero(3 * mesh.numNodes());
  const Eigen::VectorXd V = mesh.tetVolumes();
  for (int e = 0; e < mesh.numTets(); ++e)
    for (int a = 0; a < 4; ++a) b[3 * mesh.tets()(e, a) + 2] -= 1000.0 * V[e] / 4 * 9.81;
  const double scale = b.cwiseAbs().maxCoeff();
  for (Eigen::Index i = 0; i < b.size(); ++i) b[i] += 0.2 * scale * u(rng);
  for (int v : fixed_nodes) b.segment<3>(3 * v).setZero();
  return b;
}

struct Variant {
  std::string label;
  std::function<std::unique_ptr<LinearSolver>()> make;
  int interval = 1;  // coarse update interval (multigrid)
};

// "sa[:theta=T][:nu=S][:coarse=N][:unsmoothed]" → the full-set-up and the kept-prolongator variants.
std::vector<Variant> parseAggregation(const std::string& v, const Points& coordinates, const PcgOptions& pcg) {
  AggregationMultigridOptions o;
  std::string suffix;
  std::stringstream ss(v.substr(2));
  for (std::string t; std::getline(ss, t, ':');) {
    if (t.empty()) continue;
    const size_t eq = t.find('=');
    const std::string key = t.substr(0, eq), value = eq == std::string::npos ? "" : t.substr(eq + 1);
    if (key == "theta") o.strength_threshold = std::stod(value);
    else if (key == "nu") o.smoothing_steps = std::stoi(value);
    else if (key == "coarse") o.max_coarsest_dofs = std::stoi(value);
    else if (key == "unsmoothed") o.smooth_prolongator = false;
    else throw std::invalid_argument("unknown option '" + t + "' in variant '" + v + "' (theta=, nu=, coarse=, unsmoothed)");
    suffix += " " + t;
  }
  std::vector<Variant> out;
  for (const bool keep : {false, true}) {
    AggregationMultigridOptions k = o;
    k.reuse_prolongators = keep;
    out.push_back({std::string("pcg-sa ") + (keep ? "keep P" : "full") + suffix,
                   [&coordinates, pcg, k]() -> std::unique_ptr<LinearSolver> {
                     return std::make_unique<AggregationMultigridPcgSolver>(coordinates, pcg, k);
                   }});
  }
  return out;
}

// "cholmod", "pcg-jacobi" or "mg:<gs|jacobi|cheb><sweeps>[/<interval>][:key=value...]".
Variant parseVariant(const std::string& v, const MeshHierarchy& hierarchy, const PcgOptions& pcg, double damping) {
  if (v == "cholmod") return {v, [] { return std::make_unique<CholmodSolver>(); }};
  if (v == "pcg-jacobi") return {v, [pcg] { return std::make_unique<PcgSolver>(pcg); }};
  if (v.rfind("mg:", 0) == 0) {
    std::string rest = v.substr(3);
    MultigridOptions o;
    if (damping > 0) o.jacobi_damping = damping;
    // Options after the smoother: ":ratio=R" (Chebyshev interval), ":bound=B" (fine λ_max bound,
    // 0 = estimate), ":safety=S" (factor on estimated λ_max).
    std::string suffix;
    const size_t colon = rest.find(':');
    if (colon != std::string::npos) {
      std::stringstream ss(rest.substr(colon + 1));
      rest = rest.substr(0, colon);
      for (std::string t; std::getline(ss, t, ':');) {
        if (t.empty()) continue;
        const size_t eq = t.find('=');
        if (eq == std::string::npos)
          throw std::invalid_argument("option '" + t + "' in variant '" + v + "' needs a value (ratio=, bound=, safety=)");
        const std::string key = t.substr(0, eq);
        const double value = std::stod(t.substr(eq + 1));
        if (key == "ratio") o.chebyshev_ratio = value;
        else if (key == "bound") o.fine_eigenvalue_bound = value;
        else if (key == "safety") o.chebyshev_eigenvalue_safety = value;

        else throw std::invalid_argument("unknown option '" + t + "' in variant '" + v + "' (ratio=, bound=, safety=)");
        suffix += " " + t;
      }
    }
    const size_t slash = rest.find('/');
    if (slash != std::string::npos) {
      o.coarse_update_interval = std::stoi(rest.substr(slash + 1));
      rest = rest.substr(0, slash);
    }
    std::string smoother = rest;
    while (!smoother.empty() && std::isdigit(static_cast<unsigned char>(smoother.back()))) smoother.pop_back();
    const std::string sweeps = rest.substr(smoother.size());
    if (smoother == "gs") o.smoother = MultigridOptions::Smoother::kGaussSeidel;
    else if (smoother == "jacobi") o.smoother = MultigridOptions::Smoother::kJacobi;
    else if (smoother == "cheb") o.smoother = MultigridOptions::Smoother::kChebyshev;
    else throw std::invalid_argument("unknown smoother in variant '" + v + "' (gs, jacobi or cheb)");
    o.pre_smoothing_steps = o.post_smoothing_steps = sweeps.empty() ? 1 : std::stoi(sweeps);
    const std::string label = "pcg-multigrid " + smoother + "(" + std::to_string(o.pre_smoothing_steps) + "," +
                              std::to_string(o.post_smoothing_steps) + ")" +
                              (o.coarse_update_interval > 1 ? " /" + std::to_string(o.coarse_update_interval) : "") +
                              suffix;
    return {label,
            [&hierarchy, pcg, o]() -> std::unique_ptr<LinearSolver> {
              return std::make_unique<MultigridPcgSolver>(hierarchy, pcg, o);
            },
            o.coarse_update_interval};
  }
  throw std::invalid_argument("unknown variant '" + v + "' (cholmod, pcg-jacobi, mg:gs1, mg:jacobi2/4, mg:cheb2:ratio=10, ...)");
}

}  // namespace

int main(int argc, char** argv) {
  std::string case_file = std::string(BREAST_SIM_SOURCE_DIR_FOR_TOOLS) + "/config/phantom_default.yaml";
  std::string json_path;
  std::vector<int> targets = {47895};
  std::vector<std::string> variant_names = {"cholmod",   "pcg-jacobi", "mg:gs1",       "mg:gs2",
                                            "mg:jacobi1", "mg:jacobi2", "mg:jacobi1/4"};
  double tol = 1e-8, step_tol = 1e-2, rotate_deg = 0.0, poisson = 0.48;
  int repeats = 7;
  CoarseningOptions coarsening;
  coarsening.max_coarsest_elements = 300;
  bool morton = false;
  double damping = 0.0;
  auto list = [](const std::string& v) {
    std::vector<std::string> out;
    std::stringstream ss(v);
    for (std::string t; std::getline(ss, t, ',');) out.push_back(t);
    return out;
  };
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "option %s needs a value\n", k.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (k == "--case") case_file = value();
    else if (k == "--json") json_path = value();
    else if (k == "--tol") tol = std::stod(value());
    else if (k == "--step-tol") step_tol = std::stod(value());
    else if (k == "--rotate") rotate_deg = std::stod(value());
    else if (k == "--poisson") poisson = std::stod(value());
    else if (k == "--repeats") repeats = std::max(1, std::stoi(value()));
    else if (k == "--max-coarsest") coarsening.max_coarsest_elements = std::stoi(value());
    else if (k == "--size-factor") coarsening.size_factor = std::stod(value());
    else if (k == "--variants") variant_names = list(value());
    else if (k == "--morton") morton = true;
    else if (k == "--damping") damping = std::stod(value());
    else if (k == "--targets") {
      targets.clear();
      for (const std::string& t : list(value())) targets.push_back(std::stoi(t));
    } else {
      std::fprintf(stderr,
                   "unknown option %s\nusage: bench_solvers [--case FILE] [--targets N,N,...] [--tol T] [--repeats R] "
                   "[--max-coarsest N] [--size-factor F] [--variants V,V,...] [--damping W] [--morton] "
                   "[--rotate DEG] [--step-tol T] [--poisson NU] [--json FILE]\n",
                   k.c_str());
      return 2;
    }
  }

  const ModelCase base = loadModelCase(case_file);
  std::printf("case %s, %d OpenMP threads, relative tolerance %.0e (step %.0e), median of %d repeats%s", base.name.c_str(),
              omp_get_max_threads(), tol, step_tol, repeats, morton ? ", fine mesh in Morton order" : "");
  if (rotate_deg != 0.0) std::printf(", step matrix bent by up to %.0f°", rotate_deg);
  std::printf(", Poisson ratio %.3g", poisson);
  std::printf("\n");
  nlohmann::json rows = nlohmann::json::array();
  for (int target : targets) {
    ModelCase c = base;
    c.meshing.target_elements = target;
    auto t0 = Clock::now();
    SimulationModel model = buildSimulationModel(c);
    if (morton) model.mesh = mortonOrdered(model.mesh);
    const double t_fine = since(t0);
    t0 = Clock::now();
    const MeshHierarchy hierarchy = buildMeshHierarchy(c, model, coarsening);
    const double t_hierarchy = since(t0);
    const std::vector<int>& fixed = model.mesh.nodeSet(node_sets::kChestWall);
    const SparseMatrix A = implicitStepMatrix(model.mesh, fixed, 2000.0, poisson, 1000.0, 0.033);
    std::vector<double> modulus;
    const Points bent = bentPositions(model.mesh, rotate_deg, modulus);
    const SparseMatrix A_step = rotate_deg != 0.0
                                    ? implicitStepMatrix(model.mesh, fixed, 2000.0, poisson, 1000.0, 0.033, &bent, &modulus)
                                    : A;
    const Points& coordinates = model.mesh.nodes();
    const Eigen::VectorXd b = load(model.mesh, fixed, 1);
    const Eigen::VectorXd b_next = b + 0.01 * load(model.mesh, fixed, 2);  // the next step's load

    std::printf("\n%d tetrahedra, %d nodes, %ld DOFs, %ld nonzeros; meshed in %.2f s, coarse levels + "
                "prolongations in %.2f s\n",
                model.mesh.numTets(), model.mesh.numNodes(), static_cast<long>(A.rows()),
                static_cast<long>(A.nonZeros()), t_fine, t_hierarchy);
    nlohmann::json levels = nlohmann::json::array();
    for (int l = 0; l < hierarchy.numLevels(); ++l)
      levels.push_back({{"tets", hierarchy.mesh(l).numTets()}, {"nodes", hierarchy.mesh(l).numNodes()}});

    PcgOptions pcg;
    pcg.relative_tolerance = tol;
    pcg.max_iterations = 20000;
    struct Result {
      std::string label;
      double analyze_ms = 0, first_ms = 0, factorize_ms = 0, solve_ms = 0, warm_ms = 0, step_tol_ms = 0;
      int iterations = 0, warm_iterations = 0, step_tol_iterations = -1;
      double residual = 0, error = 0, vcycle_ms = 0;
      double factorize_cpu_ms = 0, solve_cpu_ms = 0, step_tol_cpu_ms = 0;  // process CPU time, medians
      bool sa = false;
      MultigridPreconditioner::Timings mg;
      AggregationMultigridPreconditioner::Timings sa_parts;
      std::vector<double> level_ms;  // per V-cycle
      std::vector<long> sa_dofs, sa_nnz;
    };
    std::vector<Result> results;
    Eigen::VectorXd x_ref;
    bool levels_printed = false;
    std::vector<Variant> variants;
    for (const std::string& name : variant_names) {
      if (name == "sa" || name.rfind("sa:", 0) == 0)
        for (Variant& v : parseAggregation(name, coordinates, pcg)) variants.push_back(std::move(v));
      else variants.push_back(parseVariant(name, hierarchy, pcg, damping));
    }
    for (const Variant& v : variants) {
      std::unique_ptr<LinearSolver> solver = v.make();
      auto* m = dynamic_cast<MultigridPcgSolver*>(solver.get());
      auto* sa = dynamic_cast<AggregationMultigridPcgSolver*>(solver.get());
      auto* pcg_solver = dynamic_cast<PcgSolver*>(solver.get());
      Result r;
      r.label = v.label;
      r.sa = sa != nullptr;
      t0 = Clock::now();
      solver->analyzePattern(A);
      r.analyze_ms = 1e3 * since(t0);
      t0 = Clock::now();
      solver->factorize(A);  // the first step (rest configuration)
      r.first_ms = 1e3 * since(t0);
      // A full set-up sees the current positions (its rigid modes); a kept P stays from the rest state.
      if (sa && !sa->multigrid().options().reuse_prolongators) sa->multigrid().setCoordinates(bent);
      std::vector<double> tf, ts, tw, tv, cf, cs, cl;
      Eigen::VectorXd x;
      const int reps = v.label == "cholmod" ? std::min(repeats, 3) : std::max(repeats, 2 * v.interval);
      std::vector<double> level_sum;
      for (int k = 0; k < reps; ++k) {
        t0 = Clock::now();
        double c0 = cpuSeconds();
        solver->factorize(A_step);
        tf.push_back(since(t0));
        cf.push_back(cpuSeconds() - c0);
        if (m && m->multigrid().lastFactorizeTimings().galerkin_s > 0) r.mg = m->multigrid().lastFactorizeTimings();
        if (sa) r.sa_parts = sa->multigrid().lastFactorizeTimings();
        x.setZero(A.rows());
        c0 = cpuSeconds();
        const SolveStats s = solver->solve(b, x);
        cs.push_back(cpuSeconds() - c0);
        ts.push_back(s.seconds);
        r.iterations = s.iterations;
        r.residual = s.relative_residual;
        const std::vector<double>* ls = nullptr;
        int apps = 0;
        if (m) ls = &m->multigrid().lastFactorizeTimings().level_s, apps = m->multigrid().lastFactorizeTimings().applications;
        if (sa) ls = &sa->multigrid().lastFactorizeTimings().level_s, apps = sa->multigrid().lastFactorizeTimings().applications;
        if (ls) {
          level_sum.resize(ls->size(), 0.0);
          double total = 0.0;
          for (size_t l = 0; l < ls->size(); ++l) {
            level_sum[l] += (*ls)[l] / std::max(apps, 1);
            total += (*ls)[l] / std::max(apps, 1);
          }
          tv.push_back(total);
        }
        Eigen::VectorXd xw = x;
        const SolveStats w = solver->solve(b_next, xw);
        tw.push_back(w.seconds);
        r.warm_iterations = w.iterations;
      }
      if (pcg_solver) {  // a cold solve to the step tolerance
        PcgOptions loose = pcg_solver->options();
        loose.relative_tolerance = step_tol;
        pcg_solver->setOptions(loose);
        std::vector<double> tl;
        for (int k = 0; k < 3; ++k) {
          Eigen::VectorXd xl = Eigen::VectorXd::Zero(A.rows());
          const double c0 = cpuSeconds();
          const SolveStats s = pcg_solver->solve(b, xl);
          cl.push_back(cpuSeconds() - c0);
          tl.push_back(s.seconds);
          r.step_tol_iterations = s.iterations;
        }
        r.step_tol_ms = 1e3 * median(tl);
        r.step_tol_cpu_ms = 1e3 * median(cl);
        pcg_solver->setOptions(pcg);
      }
      double mean = 0;
      for (double t : tf) mean += t / static_cast<double>(tf.size());
      r.factorize_ms = 1e3 * (v.interval > 1 ? mean : median(tf));
      r.solve_ms = 1e3 * median(ts);
      r.factorize_cpu_ms = 1e3 * median(cf);
      r.solve_cpu_ms = 1e3 * median(cs);
      r.warm_ms = 1e3 * median(tw);
      r.vcycle_ms = 1e3 * median(tv);
      for (double t : level_sum) r.level_ms.push_back(1e3 * t / reps);
      if (x_ref.size() == 0) x_ref = x;
      r.error = (x - x_ref).norm() / x_ref.norm();
      if (m && !levels_printed) {
        levels_printed = true;
        for (int l = 0; l < m->multigrid().numLevels(); ++l) {
          const SparseMatrix& M = m->multigrid().levelMatrix(l);
          std::printf("  level %d: %7d tetrahedra %6d nodes; operator %6ld DOFs %8ld nonzeros (%4.1f blocks per row), "
                      "%2d colours\n",
                      l, hierarchy.mesh(l).numTets(), hierarchy.mesh(l).numNodes(), static_cast<long>(M.rows()),
                      static_cast<long>(M.nonZeros()), static_cast<double>(M.nonZeros()) / 9.0 / (M.rows() / 3.0),
                      m->multigrid().numColours(l));
          levels[l]["dofs"] = M.rows();
          levels[l]["nonzeros"] = M.nonZeros();
          levels[l]["colours"] = m->multigrid().numColours(l);
        }
      }
      if (sa)
        for (int l = 0; l < sa->multigrid().numLevels(); ++l) {
          r.sa_dofs.push_back(static_cast<long>(sa->multigrid().levelMatrix(l).rows()));
          r.sa_nnz.push_back(static_cast<long>(sa->multigrid().levelMatrix(l).nonZeros()));
        }
      results.push_back(r);
    }

    const Result* jac = nullptr;
    const Result* mgj = nullptr;
    for (const Result& r : results) {
      if (r.label == "pcg-jacobi") jac = &r;
      if (r.label == "pcg-multigrid jacobi(1,1)") mgj = &r;
    }
    std::printf("\n%-32s %7s %7s %8s %8s %5s %8s %5s %8s %5s %8s %9s %9s %7s %7s %8s\n", "solver", "analyze", "first",
                "factor.", "solve", "iter", "warm", "iter", "to step", "iter", "V-cycle", "step", "warm", "vs jac",
                "vs mg1", "rel.diff");
    std::printf("%-32s %7s %7s %8s %8s %5s %8s %5s %8s %5s %8s %9s %9s %7s %7s %8s\n", "", "[ms]", "[ms]", "[ms]", "[ms]",
                "", "[ms]", "", "tol [ms]", "", "[ms]", "cold [ms]", "step [ms]", "cold", "cold", "");
    nlohmann::json solvers = nlohmann::json::array();
    for (const Result& r : results) {
      const double step = r.factorize_ms + r.solve_ms, warm_step = r.factorize_ms + r.warm_ms;
      const double ratio = jac ? (jac->factorize_ms + jac->solve_ms) / step : 0.0;
      const double warm_ratio = jac ? (jac->factorize_ms + jac->warm_ms) / warm_step : 0.0;
      const double mg_ratio = mgj ? (mgj->factorize_ms + mgj->solve_ms) / step : 0.0;
      std::printf("%-32s %7.2f %7.2f %8.2f %8.2f %5d %8.2f %5d %8.2f %5d %8.3f %9.2f %9.2f %6.1fx %6.2fx %8.1e\n",
                  r.label.c_str(), r.analyze_ms, r.first_ms, r.factorize_ms, r.solve_ms, r.iterations, r.warm_ms,
                  r.warm_iterations, r.step_tol_ms, r.step_tol_iterations, r.vcycle_ms, step, warm_step, ratio,
                  mg_ratio, r.error);
      nlohmann::json j = {{"solver", r.label},
                          {"analyze_ms", r.analyze_ms},
                          {"first_factorize_ms", r.first_ms},
                          {"factorize_ms", r.factorize_ms},
                          {"solve_ms", r.solve_ms},
                          {"iterations", r.iterations},
                          {"warm_solve_ms", r.warm_ms},
                          {"warm_iterations", r.warm_iterations},
                          {"step_tolerance_solve_ms", r.step_tol_ms},
                          {"step_tolerance_iterations", r.step_tol_iterations},
                          {"v_cycle_ms", r.vcycle_ms},
                          {"factorize_cpu_ms", r.factorize_cpu_ms},
                          {"solve_cpu_ms", r.solve_cpu_ms},
                          {"step_tolerance_solve_cpu_ms", r.step_tol_cpu_ms},
                          {"relative_residual", r.residual},
                          {"relative_difference_to_first", r.error},
                          {"speedup_vs_jacobi_cold", ratio},
                          {"speedup_vs_jacobi_warm", warm_ratio},
                          {"speedup_vs_multigrid_jacobi1_cold", mg_ratio}};
      if (r.label.rfind("pcg-multigrid", 0) == 0) {
        j["factorize_parts_ms"] = {{"scan", 1e3 * r.mg.scan_s},
                                   {"damping_estimate", 1e3 * r.mg.damping_s},
                                   {"galerkin", 1e3 * r.mg.galerkin_s},
                                   {"coarse_cholmod", 1e3 * r.mg.coarse_factorize_s}};
        j["v_cycle_level_ms"] = r.level_ms;
      }
      if (r.sa) {
        j["factorize_parts_ms"] = {{"hierarchy", 1e3 * r.sa_parts.hierarchy_s},
                                   {"galerkin", 1e3 * r.sa_parts.galerkin_s},
                                   {"scan", 1e3 * r.sa_parts.scan_s},
                                   {"damping_estimate", 1e3 * r.sa_parts.damping_s},
                                   {"coarse_cholmod", 1e3 * r.sa_parts.coarse_factorize_s}};
        j["v_cycle_level_ms"] = r.level_ms;
        j["level_dofs"] = r.sa_dofs;
        j["level_nonzeros"] = r.sa_nnz;
      }
      solvers.push_back(j);
    }
    std::printf("process CPU time [ms] (all threads; the work when OMP_NUM_THREADS=1): factorize, cold solve, "
                "cold solve to the step tolerance, their sum:\n");
    for (const Result& r : results)
      std::printf("  %-30s %8.2f %9.2f %8.2f %9.2f\n", r.label.c_str(), r.factorize_cpu_ms, r.solve_cpu_ms,
                  r.step_tol_cpu_ms, r.factorize_cpu_ms + r.step_tol_cpu_ms);
    std::printf("multigrid: factorize parts [ms] (scan + smoother set-up, damping estimate, Galerkin products, "
                "coarsest CHOLMOD) and time per V-cycle on each level [ms]:\n");
    for (const Result& r : results)
      if (r.label.rfind("pcg-multigrid", 0) == 0) {
        std::printf("  %-30s %6.2f %6.2f %6.2f %6.2f   |", r.label.c_str(), 1e3 * r.mg.scan_s, 1e3 * r.mg.damping_s,
                    1e3 * r.mg.galerkin_s, 1e3 * r.mg.coarse_factorize_s);
        for (double t : r.level_ms) std::printf(" %6.3f", t);
        std::printf("\n");
      }
    bool sa_header = false;
    for (const Result& r : results)
      if (r.sa) {
        if (!sa_header) {
          sa_header = true;
          std::printf("sa: factorize parts [ms] (aggregation + prolongators + symbolic, Galerkin, scan + float copy, "
                      "damping, coarsest CHOLMOD), levels DOFs/nonzeros, time per V-cycle on each level [ms]:\n");
        }
        std::printf("  %-30s %6.2f %6.2f %6.2f %6.2f %6.2f   |", r.label.c_str(), 1e3 * r.sa_parts.hierarchy_s,
                    1e3 * r.sa_parts.galerkin_s, 1e3 * r.sa_parts.scan_s, 1e3 * r.sa_parts.damping_s,
                    1e3 * r.sa_parts.coarse_factorize_s);
        long nnz = 0;
        for (size_t l = 0; l < r.sa_dofs.size(); ++l) {
          std::printf(" %ld/%ld", r.sa_dofs[l], r.sa_nnz[l]);
          nnz += r.sa_nnz[l];
        }
        std::printf(" (complexity %.2f) |", r.sa_nnz.empty() ? 0.0 : static_cast<double>(nnz) / r.sa_nnz[0]);
        for (double t : r.level_ms) std::printf(" %6.3f", t);
        std::printf("\n");
      }
    rows.push_back({{"target", target}, {"tets", model.mesh.numTets()}, {"nodes", model.mesh.numNodes()},
                    {"dofs", A.rows()}, {"nonzeros", A.nonZeros()}, {"levels", levels},
                    {"hierarchy_seconds", t_hierarchy}, {"solvers", solvers}});
  }
  if (!json_path.empty()) {
    nlohmann::json out = {{"benchmark", "solvers"}, {"case", base.name}, {"threads", omp_get_max_threads()},
                          {"relative_tolerance", tol}, {"step_tolerance", step_tol}, {"rotate_deg", rotate_deg}, {"poisson_ratio", poisson},
                          {"repeats", repeats}, {"morton", morton},
                          {"max_coarsest_elements", coarsening.max_coarsest_elements},
                          {"size_factor", coarsening.size_factor}, {"rows", rows}};
    std::ofstream(json_path) << out.dump(2) << '\n';
  }
  return 0;
}
