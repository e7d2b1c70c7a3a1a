#pragma once
/// @file rank_one_sum.h
/// A symmetric positive semi-definite operator applied as a sum of rank-one terms instead of a
/// matrix, and its Galerkin image on a coarser level.
///
/// Why: the average-nodal-pressure element's volumetric stiffness is Σ_n κ_n V̂_n b_n b_nᵀ, one
/// term per node star (fem/anp_tet_fem.h). Assembled, it couples nodes two element layers apart
/// (about 4× the entries of the linear tetrahedra's matrix), and every PCG iteration and multigrid
/// sweep reads all of them; applied term by term it costs two passes over the stars, about two
/// thirds of a one-ring matrix product. The solvers that take it (PcgSolver, its Jacobi and
/// multigrid preconditioners) multiply by S + R: S the one-ring matrix, R this sum.

#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/solver/linear_solver.h"

namespace breast_sim::core {

/// R = s · D (Σ_r w_r b_r b_rᵀ) D over N nodes (3 DOFs each, order x0 y0 z0 x1 …): b_r is nonzero
/// only on the nodes of term r, w_r ≥ 0, s ≥ 0 (`scale`), D = diag(free) the DOF mask (1 free,
/// 0 fixed; nullptr = every DOF free). A non-owning view: the arrays belong to the caller (e.g. the
/// element formulation) and must stay alive and unchanged while a solver uses the view.
///
/// Term r has entries [term_start[r], term_start[r + 1]); entry k is node entry_node[k] with the 3
/// values entry_vector[3k..3k+2] of b_r there. The transposed index lists, for node a, the entries
/// at a: node_entry[j] for j in [node_start[a], node_start[a + 1]), each of term node_term[j], in
/// ascending term order; they let every product gather per node, so results do not depend on the
/// thread count.
struct RankOneSum {
  int terms = 0;
  int nodes = 0;
  const int* term_start = nullptr;       ///< terms + 1
  const int* entry_node = nullptr;       ///< per entry
  const double* entry_vector = nullptr;  ///< 3 per entry
  const double* weight = nullptr;        ///< per term: w_r ≥ 0
  const int* node_start = nullptr;       ///< nodes + 1
  const int* node_term = nullptr;        ///< per transposed entry: the term
  const int* node_entry = nullptr;       ///< per transposed entry: the entry index k
  /// Optional: per transposed entry the 3 values entry_vector[3 node_entry[j] …] in node order, so
  /// the per-node pass streams them instead of gathering (withMaskApplied makes it).
  const double* node_vector = nullptr;
  double scale = 1.0;                    ///< s ≥ 0
  const double* free = nullptr;          ///< 3·nodes DOF multipliers (1 free, 0 fixed), or nullptr

  bool empty() const { return terms == 0; }
  int entries() const { return terms > 0 ? term_start[terms] : 0; }
};

/// The same operator with the mask folded into its vectors (D b_r, 3 values per entry) and no mask
/// left (free = nullptr), with node_vector set: the products then read no mask and stream both
/// passes. The vectors are written to `storage` (6 values per entry); the view points into it and
/// R's other arrays.
RankOneSum withMaskApplied(const RankOneSum& R, std::vector<double>& storage);

/// y += alpha · R x and returns alpha · xᵀ R x (x, y: 3·nodes; workspace: at least R.terms doubles).
/// Two passes: t_r = s w_r b_rᵀ D x per term, then y_a += alpha · D_a Σ_r t_r b_r[a] per node.
/// Fixed order in both passes (no atomics): the same bits for any thread count.
double addRankOneProduct(const RankOneSum& R, const double* x, double alpha, double* y, double* workspace);

/// blocks (9 per node, row-major 3×3) += the diagonal blocks of R: s Σ_r w_r D_a b_r[a] b_r[a]ᵀ D_a.
void addRankOneDiagonal(const RankOneSum& R, double* blocks);

/// R as a 3N×3N sparse matrix (column-sorted CSR): the slow reference of the products above.
SparseMatrix rankOneMatrix(const RankOneSum& R);

/// Node prolongation, #N_fine × #N_coarse (as solver/multigrid.h's NodeProlongation).
using RankOneProlongation = Eigen::SparseMatrix<double, Eigen::RowMajor, int>;

/// The Galerkin image Pᵀ R P of a rank-one sum on the next coarser level, P = node prolongation
/// ⊗ I₃ (R's own mask D applies on the fine level): Σ_r s w_r c_r c_rᵀ with c_r = Pᵀ D b_r, a
/// rank-one sum on the coarse nodes that the coarse operator is assembled with.
/// analyze() takes R's structure only (its vectors and weights may change from call to call);
/// add() streams values, in parallel over coarse rows, without allocating after the first call.
class RankOneGalerkin {
 public:
  /// @param R  the structure (terms, entries, nodes) of the sums add() will get
  /// @param P  #R.nodes × #N_coarse, kept
  /// @throws std::invalid_argument when P's rows are not R's nodes.
  void analyze(const RankOneSum& R, const RankOneProlongation& P);
  /// The coarse block pattern of the image: per coarse node I the coarse nodes it couples to
  /// (ascending, I included; symmetric), in [patternStart()[I], patternStart()[I + 1]).
  const std::vector<int>& patternStart() const { return pattern_start_; }
  const std::vector<int>& patternNodes() const { return pattern_nodes_; }
  /// coarse += Pᵀ R P. coarse is 3#N_coarse square in the block layout of fem/block_pattern.h and
  /// its pattern contains patternStart()/patternNodes().
  /// @throws std::logic_error before analyze() or for an R of another structure;
  ///         std::invalid_argument when a block of the image is missing from coarse's pattern.
  void add(const RankOneSum& R, SparseMatrix& coarse);

 private:
  RankOneProlongation P_;
  int terms_ = 0, entries_ = 0, coarse_nodes_ = 0;
  // Per term r: its coarse support S(r) (ascending) in [supp_start_[r], supp_start_[r + 1]).
  std::vector<int> supp_start_, supp_node_;
  // Per term r and entry k of r: the prolongation entries of k's node (P's CSR positions) and
  // where each goes in S(r): [map_start_[k], map_start_[k + 1]) of map_p_ / map_local_.
  std::vector<int> map_start_, map_p_, map_local_;
  // Per coarse node I: the terms whose support holds I, with I's place there.
  std::vector<int> coarse_start_, coarse_term_, coarse_local_;
  std::vector<int> pattern_start_, pattern_nodes_;
  std::vector<double> c_;                    // 3 per support entry: c_r at each coarse node of S(r)
  std::vector<std::vector<int>> slot_maps_;  // per thread: coarse node → block slot in the row, or −1
};

}  // namespace breast_sim::core
