#pragma once
// A 20×20×10 mm block on the plane z = 0 (the wall below it), in a 1 mm label image, for the
// sliding tests (test_wall_slip, test_pipeline_divergence; test_sliding uses its simulator): the block's bottom nodes
// (node set "z_min") are the wall nodes; CHOLMOD solves, so runs are exact and repeatable.

#include <cmath>
#include <cstdint>
#include <memory>
#include <set>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/model/tissue_labels.h"
#include "breast_sim/core/sliding/chest_wall_sliding.h"
#include "breast_sim/core/sliding/chest_wall_surface.h"
#include "breast_sim/core/solver/cholmod_solver.h"

namespace breast_sim::core::test_fixtures {

/// The block's simulator: co-rotated tetrahedra (ν 0.45), gravity g [m/s²], time step dt [s], CHOLMOD.
inline std::unique_ptr<DynamicSimulator> blockSimulator(const TetMesh& mesh, const Eigen::Vector3d& g_mps2, double dt_s) {
  ElasticMaterial mat;
  mat.poisson_ratio = 0.45;
  DynamicsParams p;
  p.gravity_mps2 = g_mps2;
  p.time_step_s = dt_s;
  return std::make_unique<DynamicSimulator>(mesh, std::make_unique<CorotatedTetFem>(mesh, mat), mat, p,
                                            std::make_unique<CholmodSolver>());
}

struct SlidingBlock {
  static constexpr std::uint16_t kWall = 40, kFat = 1;
  TetMesh mesh = makeBoxMesh({4, 4, 2}, {0.02, 0.02, 0.01});
  LabelImage image;
  std::shared_ptr<const ChestWallSliding> geometry;
  std::unique_ptr<DynamicSimulator> sim;
  /// @param g_mps2  gravity [m/s²]; @param dt_s  time step [s]
  /// @param x_lo_m, x_hi_m  extent of the label image along x [m]: how far the block may slide
  SlidingBlock(const Eigen::Vector3d& g_mps2, double dt_s, double x_lo_m = -0.03, double x_hi_m = 0.09) {
    const Eigen::Vector3d lo(x_lo_m, -0.03, -0.02), hi(x_hi_m, 0.05, 0.02);
    const double voxel = 1e-3;
    const Eigen::Vector3i size = ((hi - lo) / voxel).array().ceil().cast<int>() + 1;
    image = LabelImage(size, Eigen::Vector3d::Constant(voxel), lo, kFat);
    for (int k = 0; k < size.z(); ++k)
      for (int j = 0; j < size.y(); ++j)
        for (int i = 0; i < size.x(); ++i)
          if (image.indexToPhysical(Eigen::Vector3d(i, j, k)).z() < 0) image.at(i, j, k) = kWall;
    auto wall = std::make_shared<const ChestWallSurface>(image, std::set<std::uint16_t>{kWall});
    SlidingSettings s;
    s.gaussian_limit = false;
    s.thickness_limit = false;
    s.rim_band = false;
    geometry = std::make_shared<ChestWallSliding>(mesh, mesh.nodeSet("z_min"), wall, s, nullptr, TissueLabels{},
                                                  std::vector<Eigen::Vector3d>{}, Eigen::Vector3d::UnitZ());
    sim = blockSimulator(mesh, g_mps2, dt_s);
  }
  /// Mean displacement of the bottom (wall) nodes along an axis [m].
  double meanBottom(int axis) const {
    double sum = 0;
    for (int v : mesh.nodeSet("z_min")) sum += sim->state().displacement_m[3 * v + axis];
    return sum / static_cast<double>(mesh.nodeSet("z_min").size());
  }
};

}  // namespace breast_sim::core::test_fixtures
