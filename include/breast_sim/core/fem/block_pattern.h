#pragma once
/// @file block_pattern.h
/// The sparsity pattern of a 3-DOF-per-node stiffness matrix and where each element's 3×3 blocks go.

#include <vector>

#include "breast_sim/core/mesh/tet_mesh.h"
#include "breast_sim/core/solver/linear_solver.h"

namespace breast_sim::core {

/// CSR pattern of the 3N×3N matrix of a tetrahedral mesh: node I couples to node J when they share
/// an element. Rows 3I..3I+2 all hold the columns of I's neighbours in ascending node order, three
/// per neighbour, so the 3×3 block (I, J) starts in row 3I+r at rowStart(3I+r) + 3·k, where k is the
/// position of J in I's neighbour list.
class BlockPattern {
 public:
  BlockPattern() = default;
  /// @param tets  #T×4 connectivity over `num_nodes` nodes
  BlockPattern(const Tets& tets, int num_nodes);

  int numNodes() const { return static_cast<int>(neighbour_start_.size()) - 1; }
  /// A zero-valued matrix with this pattern (values to be filled by assembly).
  const SparseMatrix& matrix() const { return matrix_; }
  /// k of block (e's local node i, e's local node j), for element e: blockSlot(e)[4 i + j].
  const int* blockSlot(int e) const { return &slots_[16 * static_cast<size_t>(e)]; }
  /// Elements incident to node I, with I's local index in each: [incidentStart(I), incidentStart(I+1)).
  int incidentStart(int node) const { return incident_start_[node]; }
  int incidentElement(int k) const { return incident_[k] >> 2; }
  int incidentLocal(int k) const { return incident_[k] & 3; }
  /// Position in the CSR value array of entry (3I + r, 3J + c) of block slot k of node I.
  int valueIndex(const SparseMatrix& A, int node, int r, int k, int c) const {
    return A.outerIndexPtr()[3 * node + r] + 3 * k + c;
  }

 private:
  SparseMatrix matrix_;
  std::vector<int> neighbour_start_;
  std::vector<int> slots_;           // 16 per element
  std::vector<int> incident_start_;  // N + 1
  std::vector<int> incident_;        // element·4 + local index
};

}  // namespace breast_sim::core
