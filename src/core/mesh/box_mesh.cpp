#include "breast_sim/core/mesh/box_mesh.h"

#include <stdexcept>
#include <string>
#include <vector>

namespace breast_sim::core {

TetMesh makeBoxMesh(const Eigen::Vector3i& cells, const Eigen::Vector3d& size_m) {
  if ((cells.array() <= 0).any() || (size_m.array() <= 0).any())
    throw std::invalid_argument("makeBoxMesh: cell counts and sizes must be positive");
  const int nx = cells.x() + 1, ny = cells.y() + 1, nz = cells.z() + 1;
  auto id = [&](int i, int j, int k) { return i + nx * (j + ny * k); };
  Points x(nx * ny * nz, 3);
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i)
        x.row(id(i, j, k)) << size_m.x() * i / cells.x(), size_m.y() * j / cells.y(), size_m.z() * k / cells.z();
  // Kuhn subdivision: six tets around the diagonal from corner 0 to corner 7 (bits: x, y, z).
  const int kuhn[6][4] = {{0, 1, 3, 7}, {0, 1, 7, 5}, {0, 5, 7, 4}, {0, 3, 2, 7}, {0, 2, 6, 7}, {0, 6, 4, 7}};
  Tets t(6 * cells.prod(), 4);
  int e = 0;
  for (int k = 0; k < cells.z(); ++k)
    for (int j = 0; j < cells.y(); ++j)
      for (int i = 0; i < cells.x(); ++i) {
        int c[8];
        for (int b = 0; b < 8; ++b) c[b] = id(i + (b & 1), j + ((b >> 1) & 1), k + ((b >> 2) & 1));
        for (const auto& tet : kuhn) t.row(e++) << c[tet[0]], c[tet[1]], c[tet[2]], c[tet[3]];
      }
  TetMesh mesh(std::move(x), std::move(t));
  const char* names[3][2] = {{"x_min", "x_max"}, {"y_min", "y_max"}, {"z_min", "z_max"}};
  const int last[3] = {nx - 1, ny - 1, nz - 1};
  std::vector<int> faces[3][2], boundary;
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        const int ijk[3] = {i, j, k};
        bool on = false;
        for (int a = 0; a < 3; ++a) {
          if (ijk[a] == 0) faces[a][0].push_back(id(i, j, k)), on = true;
          if (ijk[a] == last[a]) faces[a][1].push_back(id(i, j, k)), on = true;
        }
        if (on) boundary.push_back(id(i, j, k));
      }
  for (int a = 0; a < 3; ++a)
    for (int s = 0; s < 2; ++s) mesh.setNodeSet(names[a][s], faces[a][s]);
  mesh.setNodeSet("boundary", boundary);
  return mesh;
}

}  // namespace breast_sim::core
