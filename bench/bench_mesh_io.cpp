// Mesh file I/O benchmark: TetMesh construction (boundary extraction) and write/read time of every
// format for a structured mesh of about 300k tetrahedra. Prints a table; --json FILE writes it too.
//   bench_mesh_io [--cubes N] [--json FILE]
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "breast_sim/core/mesh/mesh_io.h"

using namespace breast_sim::core;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

static double since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

int main(int argc, char** argv) {
  int n = 37;  // 6·37³ = 303,918 tets
  std::string json_path;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string k = argv[i];
    if (k == "--cubes") n = std::stoi(argv[i + 1]);
    else if (k == "--json") json_path = argv[i + 1];
    else {
      std::fprintf(stderr, "usage: bench_mesh_io [--cubes N] [--json FILE]\n");
      return 2;
    }
  }
  const int m = n + 1;
  Points x(m * m * m, 3);
  for (int i = 0; i < m * m * m; ++i) x.row(i) << 1e-3 * (i % m), 1e-3 * ((i / m) % m), 1e-3 * (i / (m * m));
  const int pattern[6][4] = {{0, 1, 3, 7}, {0, 1, 7, 5}, {0, 5, 7, 4}, {0, 3, 2, 7}, {0, 2, 6, 7}, {0, 6, 4, 7}};
  Tets tets(6 * n * n * n, 4);
  int e = 0;
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) {
        const int c0 = i + m * (j + m * k);
        const int c[8] = {c0, c0 + 1, c0 + m, c0 + m + 1, c0 + m * m, c0 + m * m + 1, c0 + m * m + m, c0 + m * m + m + 1};
        for (const auto& p : pattern) tets.row(e++) << c[p[0]], c[p[1]], c[p[2]], c[p[3]];
      }
  auto t0 = Clock::now();
  const TetMesh mesh(x, tets);
  const double construct = since(t0);
  std::printf("%d tets, %d nodes: TetMesh constructor (validation + boundary) %.3f s\n", mesh.numTets(), mesh.numNodes(), construct);
  std::printf("%-12s %9s %9s %9s\n", "file", "write[s]", "read[s]", "size[MB]");
  const fs::path dir = fs::temp_directory_path() / "breast_sim_bench_mesh_io";
  fs::create_directories(dir);
  MeshWriteOptions msh41b;
  msh41b.gmsh = {GmshVersion::kMsh41, true};
  MeshWriteOptions msh22b;
  msh22b.gmsh = {GmshVersion::kMsh22, true};
  const std::vector<std::pair<std::string, MeshWriteOptions>> cases = {
      {"m22.msh", {}}, {"m22b.msh", msh22b}, {"m41b.msh", msh41b}, {"m.vtu", {}}, {"m.vtk", {}}, {"m.inp", {}}, {"m.node", {}}};
  nlohmann::json rows = nlohmann::json::array();
  for (const auto& [file, options] : cases) {
    const std::string path = (dir / file).string();
    t0 = Clock::now();
    writeTetMesh(path, mesh, {}, 1e-3, options);
    const double w = since(t0);
    t0 = Clock::now();
    const TetMesh back = readTetMesh(path, 1e-3);
    const double r = since(t0);
    const double mb = fs::file_size(path) / 1e6;
    std::printf("%-12s %9.3f %9.3f %9.1f\n", file.c_str(), w, r, mb);
    rows.push_back({{"file", file}, {"write_s", w}, {"read_s", r}, {"megabytes", mb}, {"tets_read", back.numTets()}});
  }
  fs::remove_all(dir);
  if (!json_path.empty())
    std::ofstream(json_path) << nlohmann::json{{"benchmark", "mesh_io"}, {"tets", mesh.numTets()},
                                               {"construct_s", construct}, {"rows", rows}}.dump(2) << '\n';
  return 0;
}
