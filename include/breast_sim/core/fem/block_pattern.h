#pragma once
/// @file block_pattern.h
/// The sparsity pattern of a 3-DOF-per-node stiffness matrix and where each element's 3×3 blocks go.

#include <vector>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/solver/linear_solver.h"

namespace breast_sim::core {

/// CSR pattern of the 3N×3N matrix of a tetrahedral mesh: node I couples to node J when they share
/// an element (rings = 1), or when both share an element with a common node K (rings = 2: the
/// pattern of a formulation whose terms span a node's star, e.g. average-nodal-pressure tetrahedra,
/// fem/anp_tet_fem.h). Rows 3I..3I+2 all hold the columns of I's neighbours in ascending node order,
/// three per neighbour, so the 3×3 block (I, J) starts in row 3I+r at rowStart(3I+r) + 3·k, where k
/// is the position of J in I's neighbour list.
class BlockPattern {
 public:
  BlockPattern() = default;
  /// @param tets   #T×4 connectivity over `num_nodes` nodes
  /// @param rings  1: neighbours share an element; 2: neighbours of neighbours too
  /// @throws std::invalid_argument for rings other than 1 or 2.
  BlockPattern(const Tets& tets, int num_nodes, int rings = 1);

  int numNodes() const { return static_cast<int>(neighbour_start_.size()) - 1; }
  /// Node I's neighbours (itself included), ascending: neighbour(k) for k in
  /// [neighbourStart(I), neighbourStart(I+1)); k − neighbourStart(I) is the block slot.
  int neighbourStart(int node) const { return neighbour_start_[node]; }
  int neighbour(int k) const { return neighbours_[k]; }
  /// All neighbour lists, concatenated (neighbour(k) = neighbourData()[k]), and their starts
  /// (neighbourStarts()[I] = neighbourStart(I), N + 1 values).
  const int* neighbourData() const { return neighbours_.data(); }
  const int* neighbourStarts() const { return neighbour_start_.data(); }
  /// A zero-valued matrix with this pattern (values to be filled by assembly).
  const SparseMatrix& matrix() const { return matrix_; }
  /// k of block (e's local node i, e's local node j), for element e: blockSlot(e)[4 i + j].
  const int* blockSlot(int e) const { return &slots_[16 * static_cast<size_t>(e)]; }
  /// Elements incident to node I, with I's local index in each: [incidentStart(I), incidentStart(I+1)).
  int incidentStart(int node) const { return incident_start_[node]; }
  int incidentElement(int k) const { return incident_[k] >> 2; }
  int incidentLocal(int k) const { return incident_[k] & 3; }
  /// The same as arrays, for kernels: incidentStarts()[I] = incidentStart(I) (N + 1 values), and
  /// incidences()[k] = incidentElement(k)·4 + incidentLocal(k).
  const int* incidentStarts() const { return incident_start_.data(); }
  const int* incidences() const { return incident_.data(); }
  /// Position in the CSR value array of entry (3I + r, 3J + c) of block slot k of node I.
  int valueIndex(const SparseMatrix& A, int node, int r, int k, int c) const {
    return A.outerIndexPtr()[3 * node + r] + 3 * k + c;
  }

 private:
  SparseMatrix matrix_;
  std::vector<int> neighbour_start_;
  std::vector<int> neighbours_;      // node ids, neighbour_start_[I] .. neighbour_start_[I+1]
  std::vector<int> slots_;           // 16 per element
  std::vector<int> incident_start_;  // N + 1
  std::vector<int> incident_;        // element·4 + local index
};

}  // namespace breast_sim::core
