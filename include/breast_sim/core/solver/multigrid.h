#pragma once
/// @file multigrid.h
/// Geometric multigrid over a hierarchy of tetrahedral meshes of the same domain [GW08]: barycentric
/// prolongation, Galerkin coarse operators by a sparse triple product with a precomputed structure
/// [GW10], a symmetric V-cycle as preconditioner for CG, a direct solve on the coarsest level (dense
/// Cholesky when it is small, CHOLMOD otherwise).
///
/// [AB03] M. Adams, M. Brezina, J. Hu, R. Tuminaro: Parallel multigrid smoothing: polynomial versus
///        Gauss–Seidel. J. Comput. Phys. 188 (2003) 593–610 (Chebyshev smoother).

#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Cholesky>
#include <Eigen/SparseCore>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "breast_sim/core/solver/linear_solver.h"
#include "breast_sim/core/solver/pcg_solver.h"
#include "breast_sim/core/solver/rank_one_sum.h"

namespace breast_sim::core {

struct ModelCase;        // model/model_case.h
struct SimulationModel;  // model/model_case.h

/// Node prolongation from a coarse to a fine mesh, #N_fine × #N_coarse: row i holds the barycentric
/// weights of fine node i in the coarse element containing it (at most 4 nonzeros, summing to 1; an
/// empty row for a node in no element). The DOF prolongation is P ⊗ I₃ (the same weights for x, y, z).
using NodeProlongation = Eigen::SparseMatrix<double, Eigen::RowMajor, int>;

/// Barycentric interpolation of every fine node in the coarse mesh (model/point_embedding.h).
/// A fine node outside the coarse mesh by at most `snap_tolerance_m` (the coarse surface approximates
/// the image more coarsely) takes the clamped weights of the nearest coarse element; weights below
/// 1e-12 are dropped and the rest renormalised.
/// @param outside_distance_m  when not null, set to #N_fine distances outside the coarse mesh [m] (0 inside)
/// @throws std::invalid_argument naming the fine node and its distance when it lies farther outside.
NodeProlongation barycentricProlongation(const TetMesh& fine, const TetMesh& coarse, double snap_tolerance_m,
                                         std::vector<double>* outside_distance_m = nullptr);

/// The DOF prolongation P ⊗ I₃, 3#N_fine × 3#N_coarse (DOF order x0 y0 z0 x1 …). For tests and
/// slow references; the solver never forms it.
SparseMatrix expandToDofs(const NodeProlongation& P);

/// Meshes of one domain from fine to coarse and the prolongations between consecutive levels.
class MeshHierarchy {
 public:
  MeshHierarchy() = default;
  /// @param meshes  fine first, each next one coarser (at least one mesh); the coarse meshes are
  ///        renumbered by mortonOrdered() (the fine one is kept: it numbers the caller's DOFs)
  /// @param snap_factor  snap tolerance of level l+1 = factor × its mean boundary edge length
  /// @throws std::invalid_argument when `meshes` is empty or a fine node lies outside the next coarser
  ///         mesh by more than the tolerance (names both levels).
  explicit MeshHierarchy(std::vector<TetMesh> meshes, double snap_factor = 1.0);

  int numLevels() const { return static_cast<int>(meshes_.size()); }
  const TetMesh& mesh(int level) const { return meshes_.at(level); }
  /// Prolongation from level+1 to level, #N_level × #N_level+1; level in [0, numLevels − 2].
  const NodeProlongation& prolongation(int level) const { return prolongations_.at(level); }
  const std::vector<NodeProlongation>& prolongations() const { return prolongations_; }
  /// #N_level distances of the level's nodes outside the level+1 mesh [m] (0 inside).
  const std::vector<double>& outsideDistance(int level) const { return outside_distance_m_.at(level); }

 private:
  std::vector<TetMesh> meshes_;
  std::vector<NodeProlongation> prolongations_;
  std::vector<std::vector<double>> outside_distance_m_;
};

/// How the coarse levels are meshed.
struct CoarseningOptions {
  double size_factor = 2.0;         ///< interior element size ratio between consecutive levels
  /// Stop once a level has at most this many tetrahedra. The Galerkin operator of the coarsest
  /// level is nearly dense (its Cholesky factor is), so its factorization grows with the cube of
  /// its size.
  int max_coarsest_elements = 300;
  int max_coarse_levels = 5;        ///< never more coarse levels than this
};

/// Coarser meshes of a case's tissue for the multigrid hierarchy: meshLabelImage with the case's
/// meshing options (skin factor, grading, lesion refinement) at interior sizes
/// s × size_factor^k, k = 1, 2, …, s being the fine mesh's interior size, until a mesh has at most
/// max_coarsest_elements tetrahedra (or stops shrinking by at least 20 %).
/// @param fine  the fine model built from `model_case` (its mesh size and MeshingReport::interior_size_m)
/// @return the coarse meshes, coarsest last (empty if the fine mesh is already small enough)
/// @throws as meshLabelImage does; the message names the level and size.
std::vector<TetMesh> buildCoarseMeshes(const ModelCase& model_case, const SimulationModel& fine,
                                       const CoarseningOptions& options = {});

/// The hierarchy of the fine model's mesh and buildCoarseMeshes(model_case, fine, options).
MeshHierarchy buildMeshHierarchy(const ModelCase& model_case, const SimulationModel& fine,
                                 const CoarseningOptions& options = {}, double snap_factor = 1.0);

/// Galerkin coarse operator A_c = (D P)ᵀ A (D P) of a 3×3-block matrix [GW10]: D = diag(free) masks
/// fixed fine DOFs out of P, so the coarse space never moves them. analyze() computes the pattern of
/// A_c and, for every product term, where it comes from and where it goes; compute() then only
/// streams values, in parallel over coarse rows, without allocating: row I of Pᵀ A is summed from the
/// rows of I's fine children into a small dense buffer and multiplied by P into the upper blocks of
/// A_c's row I; the lower blocks are mirrored. Each fine row of A is read once per coarse parent (4×).
///
/// A must have the layout of fem/block_pattern.h: rows 3I, 3I+1, 3I+2 hold the same columns, three
/// per neighbour J (3J, 3J+1, 3J+2), ascending, the diagonal block included. A_c has that layout too.
/// \note Fixed DOFs must be decoupled in A (zero rows and columns off the diagonal), as the
/// LinearSolver contract says: only the rows are masked, the zero columns do the rest.
class GalerkinProduct {
 public:
  /// Symbolic phase: the pattern of A_c (zero values) and the index lists of the product.
  /// @param A  3#N_fine square, block layout (values unused)
  /// @param P  #N_fine × #N_coarse node prolongation (pattern and values are kept)
  /// @param extra_start, extra_nodes  optional: further blocks A_c's pattern must hold, per coarse
  ///        node I the nodes [extra_start[I], extra_start[I + 1]) of extra_nodes (a symmetric
  ///        pattern, e.g. RankOneGalerkin's), so that a term added after compute() has its place
  /// @throws std::invalid_argument when the sizes or A's layout do not fit.
  void analyze(const SparseMatrix& A, const NodeProlongation& P, const std::vector<int>* extra_start = nullptr,
               const std::vector<int>* extra_nodes = nullptr);
  /// Numeric phase: A_c's values from A's.
  /// @param A     same pattern as in analyze()
  /// @param free  3#N_fine DOF multipliers: 1 free, 0 fixed (nullptr = all free)
  void compute(const SparseMatrix& A, const double* free);
  /// A_c, 3#N_coarse square, block layout.
  const SparseMatrix& coarse() const { return coarse_; }
  SparseMatrix& coarse() { return coarse_; }

 private:
  NodeProlongation P_;
  std::vector<int> child_start_, child_;  // Pᵀ: fine children of each coarse node …
  std::vector<double> child_weight_;      // … and their weights
  std::vector<int> fine_start_, fine_;    // fine nodes F(I) coupled to the children of I
  std::vector<int> c_start_, c_slot_;     // per (I, child, block of A): slot in F(I)
  // Upper triangle only (parents J ≥ I); the lower one is mirrored.
  std::vector<unsigned char> g_count_;    // per (I, f ∈ F(I)): parents J ≥ I of f
  std::vector<int> g_start_, g_weight_, g_slot_;  // per such parent: index of its weight in P, block of A_c row I
  std::vector<int> diag_k_;               // per coarse node: block index of its diagonal block
  std::vector<int> mirror_start_, mirror_dst_, mirror_node_, mirror_k_;  // lower block ← transposed upper block
  int max_fine_ = 0;
  std::vector<std::vector<double>> buffers_;  // one 9·max_fine_ buffer per thread
  SparseMatrix coarse_;
  Eigen::Index fine_rows_ = 0, fine_nnz_ = 0;
};

/// Options of the V-cycle.
struct MultigridOptions {
  /// The smoother of every level but the coarsest. Jacobi is the default, the fastest per solve on
  /// the phantom: Gauss–Seidel needs fewer PCG iterations but costs more per V-cycle (a barrier per
  /// colour), Chebyshev needs fewer still at about the same time per step (the measurements:
  /// docs/benchmarks.md, docs/benchmarks/multigrid_chebyshev.md).
  enum class Smoother {
    kJacobi,      ///< damped 3×3-block Jacobi (parallel; 2 matrix passes per V(1,1) level visit)
    kGaussSeidel, ///< multicoloured 3×3-block Gauss–Seidel: forward before, backward after the
                  ///< coarse correction, so the V-cycle stays symmetric (3 matrix passes)
    /// Chebyshev polynomial of D⁻¹A [AB03], D the 3×3 block diagonal, of degree = the smoothing
    /// steps, on the interval [λ_max / chebyshev_ratio, λ_max]: the error e becomes
    /// p(D⁻¹A) e with p(t) = T_k((θ − t)/δ) / T_k(θ/δ), θ and δ the interval's centre and half
    /// width, the polynomial of degree k with p(0) = 1 that is smallest on the interval (at most
    /// 1/T_k(θ/δ) there). The same polynomial before and after the coarse correction keeps the
    /// V-cycle symmetric; |p| < 1 on the whole spectrum, so the V-cycle positive definite, as
    /// long as λ_max(D⁻¹A) < λ_max (1 + 1/ratio). Parallel like Jacobi and as cheap per step
    /// (degree k from zero: k − 1 matrix passes; from a guess: k).
    kChebyshev
  };
  Smoother smoother = Smoother::kJacobi;
  int pre_smoothing_steps = 1;   ///< sweeps (Chebyshev: the degree) before the coarse correction
  int post_smoothing_steps = 1;  ///< sweeps after it (equal to pre for a symmetric preconditioner)
  /// Chebyshev: λ_max / λ_min of the interval the polynomial damps (> 1). The modes of D⁻¹A below
  /// λ_max / ratio are left to the coarse correction. Larger ratios damp a wider band less; the
  /// error reduction on the band is 1/T_k((ratio + 1)/(ratio − 1)).
  double chebyshev_ratio = 10.0;
  /// Chebyshev on levels whose λ_max(D⁻¹A) is estimated by power iteration (which approaches it
  /// from below): λ_max = this factor × the estimate (≥ 1).
  double chebyshev_eigenvalue_safety = 1.1;
  /// ω of the Jacobi smoother; ω λ_max(D⁻¹A) < 2 keeps the smoother, and so the V-cycle,
  /// convergent. 0 = automatic: on the fine level 1.8 / fine_eigenvalue_bound; on Galerkin levels
  /// 1.2 / λ, λ estimated by power iteration at every coarse update.
  /// > 0 = this ω on every level (the caller's responsibility).
  double jacobi_damping = 0.0;
  /// An upper bound of λ_max(D⁻¹A) on the fine level, D its 3×3 block diagonal: 4 for any matrix
  /// assembled from positive semi-definite element matrices of linear tetrahedra (4 nodes each) plus
  /// a positive semi-definite block diagonal (lumped mass); 0 = estimate it like a coarse level.
  double fine_eigenvalue_bound = 4.0;
  /// Power iterations per level and coarse update for the estimate, warm-started from the last
  /// estimate's vector (the first estimate takes twelve times as many).
  int power_iterations = 3;
  /// Relative diagonal shift δ of the coarsest operator before its Cholesky factorization,
  /// A_c + δ diag(A_c). Needed because the meshes are not nested: a coarse mode that no fine node
  /// sees (a coarse element bulging out of the fine domain with fewer than four fine nodes inside)
  /// makes Pᵀ A P only semi-definite. The right-hand side of the coarse solve has no component in
  /// that null space and P removes it again, so the shift only keeps the factorization defined.
  double coarsest_diagonal_shift = 1e-9;
  /// The coarsest level of a hierarchy is solved by a dense Cholesky factorization (Eigen's LLT)
  /// when it has at most this many DOFs, by CHOLMOD otherwise. Its Galerkin operator is nearly
  /// dense, where CHOLMOD's supernodal machinery and its permuted copy cost more than the
  /// arithmetic. A dense factorization grows with the cube of the size, which bounds this
  /// (docs/benchmarks.md). 0 = always CHOLMOD.
  int dense_coarsest_max_dofs = 600;
  /// The residuals of the V-cycle by the AVX2/FMA kernel when the processor has it
  /// (solver/block_kernels.h); false = the portable scalar kernel everywhere.
  bool simd_kernels = true;
  /// The Galerkin operators and the coarsest factorization are recomputed at least in every
  /// this-many-th factorize() since the last renewal (1 = every one; coarse_update_adaptive may
  /// renew earlier); in between only the fine level takes the new matrix. The V-cycle
  /// stays symmetric positive definite with older coarse operators (Galerkin operators of an earlier
  /// SPD matrix) as long as the fine smoother converges; it converges somewhat slower when the
  /// matrix has changed much since (large rotations of the co-rotated elements). An estimated fine
  /// damping (fine_eigenvalue_bound 0) is kept too, and can be too large for a matrix that changed
  /// much: PCG then finds the V-cycle indefinite and renews it (renew()).
  int coarse_update_interval = 1;
  /// Adaptive renewal within that interval: the coarse operators are renewed early, at the next
  /// factorize(), once the PCG iterations lost to their age since the last renewal are worth a
  /// renewal (coarse_update_cost_iterations). PCG reports each solve (reportConvergence); its rate
  /// is ρ = log(‖r_k‖/‖r_0‖) / k, the log of the mean reduction per iteration, and a solve of k
  /// iterations at rate ρ lost k (1 − ρ/ρ_0) against the rate ρ_0 of the first solve after the
  /// renewal: at ρ_0 the same reduction takes k ρ/ρ_0 iterations (signed: a faster solve gives
  /// iterations back, at most one renewal's worth in all). A solve whose residual did not fall
  /// (CG's residual norm need not fall in each iteration: a capped solve of a few can end above its
  /// start) lost all its iterations; a non-finite one renews at once. The rule reads residuals
  /// only, never the clock, so a run is reproducible.
  bool coarse_update_adaptive = false;
  /// The price of a renewal in PCG iterations for the adaptive rule (> 0): the time of the Galerkin
  /// products, the coarse set-up, the damping and the coarsest factorization over the time of one
  /// PCG iteration; both grow with the mesh. The default is that ratio as measured on the phantom
  /// (docs/benchmarks.md).
  double coarse_update_cost_iterations = 5.0;
};

/// One symmetric V-cycle [GW08] as preconditioner: smoothing on each level, Galerkin coarse
/// operators (recomputed in every factorize(), or at least every coarse_update_interval-th and
/// earlier when PCG's reports say their age costs more than a renewal), a direct solve on
/// the coarsest level (dense Cholesky up to dense_coarsest_max_dofs, CHOLMOD beyond). apply() does
/// not allocate; factorize() does not after the first call, apart from the temporary permuted copy
/// CHOLMOD makes of a large coarsest matrix and the blocked dense Cholesky's workspace beyond a few
/// hundred DOFs.
///
/// The sweeps of the V-cycle (residuals, smoothing) read a copy of each level's operator in 3×3
/// blocks of floats, made in factorize(): one column index per block and 4-byte values move 2.7×
/// fewer bytes than the CSR matrix. The sweeps are then bound by instructions rather than memory, so
/// their residuals run in the AVX2/FMA kernel of solver/block_kernels.h (the measurements:
/// docs/benchmarks.md). The preconditioner stays a fixed symmetric linear operator (the values are
/// rounded once, the arithmetic is in double). PCG iterates with the fine level's float blocks at
/// loose tolerances (floatBlocks(), kFloatProductMinTolerance) but declares convergence on the
/// caller's double matrix, so the solution is as exact as with the double operator.
///
/// Fixed DOFs are found in every factorize() as the decoupled rows (no nonzero off the diagonal) of
/// each level; their prolongation rows are zero, so a coarse correction never moves them, and a
/// coarse DOF that only interpolates fixed fine DOFs gets a unit diagonal.
/// \note factorize() keeps a pointer to the fine matrix (see Preconditioner). Not thread-safe.
class MultigridPreconditioner : public Preconditioner {
 public:
  /// @param prolongations  node prolongations, fine first: level l+1 → l is prolongations[l]
  ///        (#N_l × #N_l+1); empty = a single level solved by CHOLMOD
  explicit MultigridPreconditioner(std::vector<NodeProlongation> prolongations, MultigridOptions options = {});
  explicit MultigridPreconditioner(const MeshHierarchy& hierarchy, MultigridOptions options = {});
  ~MultigridPreconditioner() override;

  /// @throws std::invalid_argument when A is not 3#N_0 square in block layout (see GalerkinProduct).
  void analyzePattern(const SparseMatrix& A) override;
  /// @throws std::logic_error when A's pattern changed; std::runtime_error "multigrid: …" when a
  ///         diagonal block of some level is not positive definite or the coarsest level's
  ///         factorization (dense Cholesky or CHOLMOD) fails.
  void factorize(const SparseMatrix& A) override;
  void apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) override;
  std::string name() const override { return "multigrid"; }
  /// Records PCG's convergence for the adaptive coarse renewal (MultigridOptions::coarse_update_adaptive).
  void reportConvergence(int iterations, double residual_reduction) override;
  /// Renews the coarse operators of the last factorize()'s matrix and estimates every estimated
  /// damping again from a cold start (the warm start's vector may miss a mode the new matrix
  /// grew). Between renewals the Galerkin operators and the dampings of an earlier matrix stay; a
  /// damping estimated for it (the fine level's too with fine_eigenvalue_bound 0, as for the
  /// average-nodal-pressure element) can be too large for a matrix that has changed much since
  /// (the moduli of a stiffened step, the wall released onto its sliding springs), and then the
  /// smoother and the V-cycle are not convergent. False when nothing is kept from an earlier matrix
  /// (the last factorize() renewed, or a single level).
  bool renew() override;

  /// A = S + R with R a rank-one sum (solver/rank_one_sum.h), e.g. the average-nodal-pressure
  /// element's volumetric stiffness: the fine level's smoother and residuals add R's products (in
  /// double) to the float blocks of S, its diagonal blocks include R's, and the first coarse
  /// operator is the Galerkin product of S plus R's Galerkin image (RankOneGalerkin), so every
  /// coarse level sees R exactly. Taken with the Jacobi and Chebyshev smoothers on two or more
  /// levels (Gauss–Seidel would need R's rows one by one).
  bool acceptsRankOneSum() const override;
  /// @throws std::logic_error when !acceptsRankOneSum(); otherwise as analyzePattern().
  void analyzeWithRankOne(const SparseMatrix& S, const RankOneSum& R) override;
  /// @throws as factorize(); std::logic_error for an R of another structure than analysed.
  void factorizeWithRankOne(const SparseMatrix& S, const RankOneSum& R) override;
  /// The fine level's float blocks (with two or more levels, after factorize()).
  FloatBlocks floatBlocks() const override;

  int numLevels() const { return static_cast<int>(levels_.size()); }
  /// How many factorize() calls renewed the coarse operators (the first one included).
  long coarseRenewals() const { return coarse_renewals_; }
  /// PCG iterations lost to the coarse operators' age since the last renewal (the adaptive rule's sum).
  double lostIterationsSinceRenewal() const { return lost_iterations_; }
  /// Operator of a level after factorize(): 0 = the caller's matrix, ≥ 1 Galerkin operators
  /// (with unit diagonals on DOFs that only interpolate fixed DOFs; the coarsest with its shift).
  const SparseMatrix& levelMatrix(int level) const;
  /// Colours of the Gauss–Seidel ordering of a level.
  int numColours(int level) const;
  /// Jacobi damping ω in use on a level (after factorize(); 0 for the coarsest).
  double jacobiDamping(int level) const;
  /// Upper end λ_max of the Chebyshev interval of a level (after factorize() with that smoother:
  /// fine_eigenvalue_bound on the fine level, else the safety factor × the power-iteration
  /// estimate; 0 for other smoothers and for the coarsest level).
  double chebyshevEigenvalueBound(int level) const;
  /// The pre-smoothing of one smoothed level alone, from x = 0 (pre_smoothing_steps sweeps, or the
  /// Chebyshev polynomial of that degree), with the level's operator: for tests and diagnostics.
  /// @param b  3#N_level right-hand side;  @param x  set to the smoothed approximation of A_level⁻¹ b
  /// @throws std::logic_error before factorize(); std::out_of_range for the coarsest or a missing level.
  void smoothOnly(int level, const Eigen::VectorXd& b, Eigen::VectorXd& x);
  const MultigridOptions& options() const { return options_; }

  /// Where the time goes [s]: the parts of the last factorize() and of the apply() calls since.
  struct Timings {
    double scan_s = 0.0;              ///< fixed-DOF detection and smoother set-up, all levels
    double damping_s = 0.0;           ///< power iterations for the Jacobi damping
    double galerkin_s = 0.0;          ///< triple products, all levels
    double coarse_factorize_s = 0.0;  ///< the coarsest level's factorization (dense or CHOLMOD)
    int applications = 0;             ///< apply() calls since that factorize()
    /// Per level, summed over those calls: its own smoothing, residual and transfers (the coarsest:
    /// its direct solve), without the levels below.
    std::vector<double> level_s;
  };
  const Timings& lastFactorizeTimings() const { return timings_; }

 private:
  struct Level;
  void scanLevel(int level);
  void estimateDamping(int level);
  void vcycle(int level, const double* b, double* x);
  void smooth(int level, const double* b, double* x, bool forward, bool from_zero);
  void chebyshev(int level, const double* b, double* x, int degree, bool from_zero);
  void residual(int level, const double* b, const double* x, double* t);
  void toBlocks(int level);
  void analyzeLevels(const SparseMatrix& A, const std::vector<int>* extra_start, const std::vector<int>* extra_nodes);
  void factorizeLevels(const SparseMatrix& A);

  MultigridOptions options_;
  std::vector<NodeProlongation> prolongations_;
  std::vector<std::unique_ptr<Level>> levels_;
  std::vector<GalerkinProduct> galerkin_;
  CholmodSolver coarsest_{CholmodOptions{1}};
  bool dense_coarsest_ = false;          // the coarsest level by Eigen's dense Cholesky (see options)
  Eigen::MatrixXd coarsest_dense_;
  Eigen::LLT<Eigen::MatrixXd> coarsest_llt_;
  Eigen::Index fine_nnz_ = -1;
  std::vector<int> fine_outer_;  // the fine matrix's row starts at analyzePattern()
  // Coarse renewal: fine-only factorizations since the last one, renewals so far, whether the next
  // factorize() renews (the first after analyzePattern(), or asked by the adaptive rule), and the
  // rule's convergence record (coarse_update_adaptive).
  int fine_only_ = 0;
  long coarse_renewals_ = 0;
  bool renew_requested_ = false;
  int rate_count_ = 0;
  double first_log_rate_ = 0.0, lost_iterations_ = 0.0;
  bool factorized_ = false;
  Timings timings_;
  // A = S + R (analyzeWithRankOne): the view of the last factorize, R's image on level 1, R's
  // diagonal blocks on level 0 (9 per node), the per-term workspace and b − R x for the Chebyshev sweep.
  bool rank_one_ = false;
  RankOneSum R_;
  int rank_one_terms_ = 0, rank_one_entries_ = 0;
  RankOneGalerkin rank_one_galerkin_;
  std::vector<double> rank_one_diag_, rank_one_work_;
  Eigen::VectorXd rank_one_rhs_;
};

/// PCG with the multigrid V-cycle as preconditioner: the LinearSolver "pcg-multigrid". The
/// prolongations are copied: the hierarchy need not outlive the solver.
class MultigridPcgSolver : public PcgSolver {
 public:
  MultigridPcgSolver(const MeshHierarchy& hierarchy, PcgOptions pcg_options = {},
                     MultigridOptions multigrid_options = {});
  MultigridPcgSolver(std::vector<NodeProlongation> prolongations, PcgOptions pcg_options = {},
                     MultigridOptions multigrid_options = {});
  MultigridPreconditioner& multigrid() { return static_cast<MultigridPreconditioner&>(preconditioner()); }
  const MultigridPreconditioner& multigrid() const {
    return static_cast<const MultigridPreconditioner&>(preconditioner());
  }
};

}  // namespace breast_sim::core
