#include "breast_sim/core/fem/block_pattern.h"

#include <algorithm>
#include <stdexcept>
#include <string>

namespace breast_sim::core {

BlockPattern::BlockPattern(const Tets& tets, int num_nodes, int rings) {
  if (rings != 1 && rings != 2)
    throw std::invalid_argument("BlockPattern: rings = " + std::to_string(rings) + "; use 1 (element neighbours) or 2");
  const int nt = static_cast<int>(tets.rows());
  // Node → incident elements (with the local index), by counting sort.
  incident_start_.assign(num_nodes + 1, 0);
  for (int e = 0; e < nt; ++e)
    for (int i = 0; i < 4; ++i) ++incident_start_[tets(e, i) + 1];
  for (int n = 0; n < num_nodes; ++n) incident_start_[n + 1] += incident_start_[n];
  incident_.resize(static_cast<size_t>(nt) * 4);
  {
    std::vector<int> fill(incident_start_.begin(), incident_start_.end() - 1);
    for (int e = 0; e < nt; ++e)
      for (int i = 0; i < 4; ++i) incident_[fill[tets(e, i)]++] = e * 4 + i;
  }
  // Node → sorted unique neighbours (including itself).
  neighbour_start_.assign(num_nodes + 1, 0);
  std::vector<std::vector<int>> nbrs(num_nodes);
#pragma omp parallel for schedule(dynamic, 256)
  for (int n = 0; n < num_nodes; ++n) {
    auto& v = nbrs[n];
    for (int k = incident_start_[n]; k < incident_start_[n + 1]; ++k) {
      const int e = incident_[k] >> 2;
      for (int j = 0; j < 4; ++j) v.push_back(tets(e, j));
    }
    if (v.empty()) v.push_back(n);  // an unused node keeps its diagonal
    std::sort(v.begin(), v.end());
    v.erase(std::unique(v.begin(), v.end()), v.end());
  }
  if (rings == 2) {
    // Neighbours of neighbours: the union of the 1-ring lists of I's 1-ring.
    std::vector<std::vector<int>> wide(num_nodes);
#pragma omp parallel for schedule(dynamic, 256)
    for (int n = 0; n < num_nodes; ++n) {
      auto& v = wide[n];
      for (const int m : nbrs[n]) v.insert(v.end(), nbrs[m].begin(), nbrs[m].end());
      std::sort(v.begin(), v.end());
      v.erase(std::unique(v.begin(), v.end()), v.end());
    }
    nbrs.swap(wide);
  }
  for (int n = 0; n < num_nodes; ++n) neighbour_start_[n + 1] = neighbour_start_[n] + static_cast<int>(nbrs[n].size());
  neighbours_.resize(neighbour_start_[num_nodes]);
  for (int n = 0; n < num_nodes; ++n) std::copy(nbrs[n].begin(), nbrs[n].end(), neighbours_.begin() + neighbour_start_[n]);

  // CSR arrays directly: row 3n + r holds 3 columns per neighbour.
  const long nnz = 9L * neighbour_start_[num_nodes];
  matrix_.resize(3 * num_nodes, 3 * num_nodes);
  matrix_.resizeNonZeros(nnz);
  int* outer = matrix_.outerIndexPtr();
  int* inner = matrix_.innerIndexPtr();
  outer[0] = 0;
  for (int n = 0; n < num_nodes; ++n) {
    const int deg = static_cast<int>(nbrs[n].size());
    for (int r = 0; r < 3; ++r) {
      const int row = 3 * n + r;
      outer[row + 1] = outer[row] + 3 * deg;
      for (int k = 0; k < deg; ++k)
        for (int c = 0; c < 3; ++c) inner[outer[row] + 3 * k + c] = 3 * nbrs[n][k] + c;
    }
  }
  std::fill(matrix_.valuePtr(), matrix_.valuePtr() + nnz, 0.0);

  slots_.resize(static_cast<size_t>(nt) * 16);
#pragma omp parallel for schedule(static)
  for (int e = 0; e < nt; ++e)
    for (int i = 0; i < 4; ++i) {
      const auto& v = nbrs[tets(e, i)];
      for (int j = 0; j < 4; ++j)
        slots_[16 * static_cast<size_t>(e) + 4 * i + j] =
            static_cast<int>(std::lower_bound(v.begin(), v.end(), tets(e, j)) - v.begin());
    }
}

}  // namespace breast_sim::core
