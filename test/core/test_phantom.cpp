#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <queue>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Geometry>

#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/model/tissue_labels.h"

using namespace breast_sim::core;

namespace {

const double kPi = 3.14159265358979323846;

std::string configPath(const std::string& name) {
  return std::string(BREAST_SIM_TEST_DATA_DIR) + "/../../config/" + name;
}

bool isTissueLabel(std::uint16_t l) {
  return l == phantom_labels::kFat || l == phantom_labels::kGland || l == phantom_labels::kSkin ||
         l == phantom_labels::kLesion;
}

long countLabel(const LabelImage& img, bool (*pred)(std::uint16_t)) {
  long n = 0;
  for (std::uint16_t l : img.labels) n += pred(l) ? 1 : 0;
  return n;
}

double voxelVolume(const LabelImage& img) { return img.spacing_m.prod(); }

/// Cases grouped by property: the default planar breast, the same at 2 mm, a curved two-breast case,
/// and one with skin, supersampling and a right-side breast.
std::vector<std::pair<std::string, PhantomParams>> phantomCases() {
  std::vector<std::pair<std::string, PhantomParams>> cases;
  PhantomParams planar2;
  planar2.voxel_size_m = 2e-3;
  cases.emplace_back("planar, 2 mm voxels", planar2);

  PhantomParams curved = loadPhantomParams(configPath("phantom_two_breasts.yaml"));
  curved.voxel_size_m = 2e-3;
  cases.emplace_back("two breasts on a curved wall, 2 mm voxels", curved);

  PhantomParams skin;
  skin.voxel_size_m = 2e-3;
  skin.skin_thickness_m = 3e-3;
  skin.supersampling = 2;
  skin.side = BreastSide::kRight;
  skin.lesions = {};
  skin.supine_gravity_tilt_rad = -0.2;
  cases.emplace_back("right breast with skin, 2x2x2 supersampling", skin);

  PhantomParams single_curved;
  single_curved.chest_wall_shape = ChestWallShape::kCylindrical;
  single_curved.chest_wall_radius_m = 0.15;
  single_curved.voxel_size_m = 2e-3;
  cases.emplace_back("single breast on a curved wall, 2 mm voxels", single_curved);
  return cases;
}

/// Slow reference: enclosed volume by the divergence theorem, Σ a·(b × c) / 6.
double enclosedVolume(const PhantomSurface& s) {
  double v = 0.0;
  for (Eigen::Index f = 0; f < s.triangles.rows(); ++f) {
    const Eigen::Vector3d a = s.vertices_m.row(s.triangles(f, 0)).transpose();
    const Eigen::Vector3d b = s.vertices_m.row(s.triangles(f, 1)).transpose();
    const Eigen::Vector3d c = s.vertices_m.row(s.triangles(f, 2)).transpose();
    v += a.dot(b.cross(c)) / 6.0;
  }
  return v;
}

/// Each directed edge used once and its reverse once.
bool everyEdgeHasOneOppositePartner(const Triangles& t) {
  std::map<std::pair<int, int>, int> directed;
  for (Eigen::Index f = 0; f < t.rows(); ++f)
    for (int e = 0; e < 3; ++e) ++directed[{t(f, e), t(f, (e + 1) % 3)}];
  for (const auto& [edge, count] : directed) {
    if (count != 1) return false;
    const auto rev = directed.find({edge.second, edge.first});
    if (rev == directed.end() || rev->second != 1) return false;
  }
  return true;
}

/// Number of 6-connected components of tissue voxels.
int tissueComponents(const LabelImage& img) {
  std::vector<char> seen(img.labels.size(), 0);
  int components = 0;
  for (int k = 0; k < img.size.z(); ++k)
    for (int j = 0; j < img.size.y(); ++j)
      for (int i = 0; i < img.size.x(); ++i) {
        if (seen[img.index(i, j, k)] || !isTissueLabel(img.at(i, j, k))) continue;
        ++components;
        std::queue<Eigen::Vector3i> q;
        q.push({i, j, k});
        seen[img.index(i, j, k)] = 1;
        while (!q.empty()) {
          const Eigen::Vector3i v = q.front();
          q.pop();
          for (int d = 0; d < 6; ++d) {
            Eigen::Vector3i w = v;
            w[d / 2] += (d % 2) ? 1 : -1;
            if (!img.contains(w.x(), w.y(), w.z())) continue;
            const long id = img.index(w.x(), w.y(), w.z());
            if (seen[id] || !isTissueLabel(img.labels[id])) continue;
            seen[id] = 1;
            q.push(w);
          }
        }
      }
  return components;
}

std::string writeCase(const std::string& name, const std::string& text) {
  const std::string path = ::testing::TempDir() + "/phantom_case_" + name + ".yaml";
  std::ofstream(path) << text;
  return path;
}

/// The message of the error loadPhantomParams throws, or "" if it throws none.
std::string loadError(const std::string& path) {
  try {
    loadPhantomParams(path);
  } catch (const std::runtime_error& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST(Phantom, DefaultCaseFileEqualsTheBuiltInDefaults) {
  const PhantomParams file = loadPhantomParams(configPath("phantom_default.yaml"));
  const PhantomParams def;
  EXPECT_EQ(file.num_breasts, def.num_breasts);
  EXPECT_EQ(file.side, def.side);
  EXPECT_EQ(file.chest_wall_shape, def.chest_wall_shape);
  EXPECT_DOUBLE_EQ(file.breast_separation_m, def.breast_separation_m);
  EXPECT_DOUBLE_EQ(file.chest_wall_radius_m, def.chest_wall_radius_m);
  EXPECT_DOUBLE_EQ(file.chest_wall_thickness_m, def.chest_wall_thickness_m);
  EXPECT_DOUBLE_EQ(file.lateral_semi_axis_m, def.lateral_semi_axis_m);
  EXPECT_DOUBLE_EQ(file.si_semi_axis_m, def.si_semi_axis_m);
  EXPECT_DOUBLE_EQ(file.depth_m, def.depth_m);
  EXPECT_DOUBLE_EQ(file.gland_scale, def.gland_scale);
  EXPECT_DOUBLE_EQ(file.skin_thickness_m, def.skin_thickness_m);
  EXPECT_DOUBLE_EQ(file.supine_depth_scale, def.supine_depth_scale);
  EXPECT_DOUBLE_EQ(file.supine_lateral_share, def.supine_lateral_share);
  EXPECT_DOUBLE_EQ(file.supine_lateral_shift_m, def.supine_lateral_shift_m);
  EXPECT_NEAR(file.supine_gravity_tilt_rad, def.supine_gravity_tilt_rad, 1e-15);
  EXPECT_DOUBLE_EQ(file.gravity_mps2, def.gravity_mps2);
  EXPECT_DOUBLE_EQ(file.voxel_size_m, def.voxel_size_m);
  EXPECT_DOUBLE_EQ(file.margin_m, def.margin_m);
  EXPECT_EQ(file.supersampling, def.supersampling);
  EXPECT_DOUBLE_EQ(file.surface_edge_m, def.surface_edge_m);
  ASSERT_EQ(file.lesions.size(), def.lesions.size());
  for (std::size_t i = 0; i < def.lesions.size(); ++i) {
    SCOPED_TRACE("lesion " + def.lesions[i].name);
    EXPECT_EQ(file.lesions[i].name, def.lesions[i].name);
    EXPECT_LT((file.lesions[i].position_m - def.lesions[i].position_m).norm(), 1e-12);
    EXPECT_DOUBLE_EQ(file.lesions[i].radius_m, def.lesions[i].radius_m);
  }
}

TEST(Phantom, DefaultCaseIsAHalfEllipsoidOfAbout480CubicCentimetres) {
  const Phantom ph = generatePhantom(loadPhantomParams(configPath("phantom_default.yaml")));
  ASSERT_EQ(ph.prone_breasts.size(), 1u);
  EXPECT_NEAR(ph.prone_volume_m3, 2.0 / 3.0 * kPi * 0.06 * 0.055 * 0.07, 1e-15);
  EXPECT_NEAR(ph.prone_volume_m3 * 1e6, 483.8, 0.1);  // cm³
  const long tissue = countLabel(ph.labels, isTissueLabel);
  const double voxel_volume = tissue * voxelVolume(ph.labels);
  EXPECT_NEAR(voxel_volume / ph.prone_volume_m3, 1.0, 0.02);
  // At least 3 voxels of air on every side.
  const LabelImage& img = ph.labels;
  for (int k = 0; k < img.size.z(); ++k)
    for (int j = 0; j < img.size.y(); ++j)
      for (int i = 0; i < img.size.x(); ++i) {
        const bool border = i < 3 || j < 3 || k < 3 || i >= img.size.x() - 3 || j >= img.size.y() - 3 ||
                            k >= img.size.z() - 3;
        if (border && isTissueLabel(img.at(i, j, k))) FAIL() << "tissue voxel within 3 voxels of the border";
      }
  std::printf("default phantom: image %d x %d x %d voxels of %.1f mm, %ld tissue voxels; volume analytic "
              "%.2f cm^3, voxels %.2f cm^3 (%+.3f%%); supine %.2f cm^3; prone surface %ld triangles, "
              "supine %ld\n",
              img.size.x(), img.size.y(), img.size.z(), img.spacing_m.x() * 1e3, tissue, ph.prone_volume_m3 * 1e6,
              voxel_volume * 1e6, 100.0 * (voxel_volume / ph.prone_volume_m3 - 1.0), ph.supine_volume_m3 * 1e6,
              static_cast<long>(ph.prone_surface.triangles.rows()),
              static_cast<long>(ph.supine_surface.triangles.rows()));
}

TEST(Phantom, GenerationIsDeterministic) {
  PhantomParams p = loadPhantomParams(configPath("phantom_two_breasts.yaml"));
  p.voxel_size_m = 2e-3;
  p.supersampling = 2;
  const Phantom a = generatePhantom(p);
  const Phantom b = generatePhantom(p);
  EXPECT_EQ(a.labels.size, b.labels.size);
  EXPECT_EQ(a.labels.origin_m, b.labels.origin_m);
  EXPECT_TRUE(a.labels.labels == b.labels.labels);
  EXPECT_EQ(a.prone_surface.vertices_m, b.prone_surface.vertices_m);
  EXPECT_EQ(a.supine_surface.triangles, b.supine_surface.triangles);
  EXPECT_EQ(a.prone_volume_m3, b.prone_volume_m3);
  EXPECT_EQ(a.supine_volume_m3, b.supine_volume_m3);
}

TEST(Phantom, VoxelVolumeIsWithinTwoPercentOfTheAnalyticVolume) {
  for (const auto& [name, params] : phantomCases()) {
    SCOPED_TRACE(name);
    const Phantom ph = generatePhantom(params);
    const double voxel_volume = countLabel(ph.labels, isTissueLabel) * voxelVolume(ph.labels);
    EXPECT_NEAR(voxel_volume / ph.prone_volume_m3, 1.0, 0.02);
  }
}

TEST(Phantom, SupineShapeHasTheProneVolumeAndIsFlatterWiderAndShiftedLaterally) {
  for (const auto& [name, params] : phantomCases()) {
    SCOPED_TRACE(name);
    const Phantom ph = generatePhantom(params);
    EXPECT_NEAR(ph.supine_volume_m3 / ph.prone_volume_m3, 1.0, 0.01);
    for (std::size_t i = 0; i < ph.prone_breasts.size(); ++i) {
      SCOPED_TRACE("breast " + std::to_string(i));
      const HalfEllipsoid& pr = ph.prone_breasts[i];
      const HalfEllipsoid& su = ph.supine_breasts[i];
      EXPECT_NEAR(su.volume() / pr.volume(), 1.0, 1e-9);
      EXPECT_LT(su.depth_m, pr.depth_m);
      EXPECT_GT(su.lateral_m, pr.lateral_m);
      EXPECT_GT(su.si_m, pr.si_m);
      if (params.chest_wall_shape == ChestWallShape::kPlanar) {
        EXPECT_NEAR(su.lateral_m * su.si_m * su.depth_m / (pr.lateral_m * pr.si_m * pr.depth_m), 1.0, 1e-12);
      }
      // Lateral = away from the sternum (x = 0); a single breast's lateral side is given by `side`.
      const double lateral = ph.prone_breasts.size() == 2 ? (pr.base_centre_m.x() > 0 ? 1.0 : -1.0)
                                                          : (params.side == BreastSide::kLeft ? 1.0 : -1.0);
      if (params.chest_wall_shape == ChestWallShape::kPlanar) {
        EXPECT_NEAR(lateral * (su.base_centre_m.x() - pr.base_centre_m.x()), params.supine_lateral_shift_m, 1e-12);
      } else {  // arc length along the cylinder
        const double R = params.chest_wall_radius_m;
        const auto angle = [R](const Eigen::Vector3d& c) { return std::atan2(c.x(), R - c.y()); };
        EXPECT_NEAR(lateral * R * (angle(su.base_centre_m) - angle(pr.base_centre_m)), params.supine_lateral_shift_m,
                    1e-12);
      }
      // Both attached to the wall.
      EXPECT_NEAR(ph.chest_wall.surfaceY(su.base_centre_m.x()), su.base_centre_m.y(), 1e-12);
      EXPECT_NEAR(ph.chest_wall.surfaceY(pr.base_centre_m.x()), pr.base_centre_m.y(), 1e-12);
    }
  }
}

TEST(Phantom, GravityPointsAnteriorProneAndPosteriorTiltedSupine) {
  for (const auto& [name, params] : phantomCases()) {
    SCOPED_TRACE(name);
    const Phantom ph = generatePhantom(params);
    EXPECT_LT((ph.gravity_prone_mps2 - Eigen::Vector3d(0, -params.gravity_mps2, 0)).norm(), 1e-12);
    EXPECT_NEAR(ph.gravity_supine_mps2.norm(), params.gravity_mps2, 1e-12);
    EXPECT_GT(ph.gravity_supine_mps2.y(), 0.0);
    EXPECT_EQ(ph.gravity_supine_mps2.z(), 0.0);
    EXPECT_NEAR(std::atan2(ph.gravity_supine_mps2.x(), ph.gravity_supine_mps2.y()), params.supine_gravity_tilt_rad,
                1e-12);
  }
}

TEST(Phantom, NipplesAreAtTheApexOnTopOfTissue) {
  for (const auto& [name, params] : phantomCases()) {
    SCOPED_TRACE(name);
    const Phantom ph = generatePhantom(params);
    ASSERT_EQ(ph.nipples_m.size(), ph.prone_breasts.size());
    for (std::size_t i = 0; i < ph.nipples_m.size(); ++i) {
      const HalfEllipsoid& e = ph.prone_breasts[i];
      const Eigen::Vector3d& nip = ph.nipples_m[i];
      EXPECT_LT((nip - (e.base_centre_m + e.depth_m * e.depth_axis)).norm(), 1e-12);
      const double h = params.voxel_size_m;
      EXPECT_TRUE(ph.insideProne(nip - 1e-6 * e.depth_axis));
      EXPECT_FALSE(ph.insideProne(nip + 1e-6 * e.depth_axis));
      EXPECT_TRUE(isTissueLabel(ph.labels.labelAt(nip - 0.75 * h * e.depth_axis)));
      EXPECT_EQ(ph.labels.labelAt(nip + 0.75 * h * e.depth_axis), phantom_labels::kAir);
    }
    // On the planar wall the apex is the most anterior point of the tissue.
    if (params.chest_wall_shape == ChestWallShape::kPlanar) {
      double min_y = 1.0;
      for (Eigen::Index v = 0; v < ph.prone_surface.vertices_m.rows(); ++v)
        min_y = std::min(min_y, ph.prone_surface.vertices_m(v, 1));
      EXPECT_NEAR(min_y, ph.nipples_m[0].y(), 1e-12);
    }
  }
}

TEST(Phantom, LesionsLieInsideTheTissueAndArePaintedWhenTheyHaveARadius) {
  const Phantom ph = generatePhantom(loadPhantomParams(configPath("phantom_default.yaml")));
  ASSERT_EQ(ph.lesions.size(), 2u);
  double painted = 0.0;
  for (const Lesion& l : ph.lesions) {
    SCOPED_TRACE(l.name);
    EXPECT_TRUE(ph.insideProne(l.position_m));
    EXPECT_GT(l.radius_m, 0.0);
    EXPECT_EQ(ph.labels.labelAt(l.position_m), phantom_labels::kLesion);
    painted += 4.0 / 3.0 * kPi * std::pow(l.radius_m, 3);
  }
  const long lesion_voxels = countLabel(ph.labels, [](std::uint16_t l) { return l == phantom_labels::kLesion; });
  EXPECT_NEAR(lesion_voxels * voxelVolume(ph.labels) / painted, 1.0, 0.1);
  // Other labels are present too: fat around a fibroglandular core, the chest wall behind.
  EXPECT_GT(countLabel(ph.labels, [](std::uint16_t l) { return l == phantom_labels::kGland; }), 0);
  EXPECT_GT(countLabel(ph.labels, [](std::uint16_t l) { return l == phantom_labels::kFat; }), 0);
  EXPECT_EQ(countLabel(ph.labels, [](std::uint16_t l) { return l == phantom_labels::kSkin; }), 0);
}

TEST(Phantom, SurfacesAreClosedOutwardAndEncloseTheAnalyticVolume) {
  for (const auto& [name, params] : phantomCases()) {
    const Phantom ph = generatePhantom(params);
    for (const auto& [shape, surface, volume, breasts] :
         {std::make_tuple("prone", &ph.prone_surface, ph.prone_volume_m3, &ph.prone_breasts),
          std::make_tuple("supine", &ph.supine_surface, ph.supine_volume_m3, &ph.supine_breasts)}) {
      SCOPED_TRACE(name + ", " + shape);
      ASSERT_EQ(static_cast<Eigen::Index>(surface->is_skin.size()), surface->triangles.rows());
      EXPECT_TRUE(everyEdgeHasOneOppositePartner(surface->triangles));
      EXPECT_TRUE(isClosedManifold(surface->triangles));
      EXPECT_NEAR(enclosedVolume(*surface) / volume, 1.0, 0.01);
      EXPECT_LT(enclosedVolume(*surface), volume);  // an inscribed polyhedron
      // Skin vertices lie on an ellipsoid, base vertices on the wall; skin normals face away from the wall.
      int skin = 0, base = 0;
      for (Eigen::Index f = 0; f < surface->triangles.rows(); ++f) {
        const Eigen::Vector3d a = surface->vertices_m.row(surface->triangles(f, 0)).transpose();
        const Eigen::Vector3d b = surface->vertices_m.row(surface->triangles(f, 1)).transpose();
        const Eigen::Vector3d c = surface->vertices_m.row(surface->triangles(f, 2)).transpose();
        const Eigen::Vector3d centroid = (a + b + c) / 3.0;
        if (surface->is_skin[f]) {
          ++skin;
          double best = 1e9;
          for (const HalfEllipsoid& e : *breasts) {
            const Eigen::Vector3d l = e.localCoordinates(a);
            best = std::min(best, std::abs(std::pow(l.x() / e.lateral_m, 2) + std::pow(l.y() / e.si_m, 2) +
                                           std::pow(l.z() / e.depth_m, 2) - 1.0));
          }
          EXPECT_LT(best, 1e-9);
        } else {
          ++base;
          EXPECT_NEAR(a.y(), ph.chest_wall.surfaceY(a.x()), 1e-9);
          EXPECT_GT((b - a).cross(c - a).dot(Eigen::Vector3d(0, 1, 0)), 0.0);  // into the chest
        }
        (void)centroid;
      }
      EXPECT_GT(skin, 0);
      EXPECT_GT(base, 0);
    }
  }
}

TEST(Phantom, ChestWallVoxelsLieDirectlyBehindTheBreastBase) {
  for (const auto& [name, params] : phantomCases()) {
    SCOPED_TRACE(name);
    const Phantom ph = generatePhantom(params);
    const LabelImage& img = ph.labels;
    int columns = 0;
    for (const HalfEllipsoid& e : ph.prone_breasts) {
      for (double fu : {-0.8, -0.4, 0.0, 0.4, 0.8})
        for (double fv : {-0.5, 0.0, 0.5}) {
          // A point just anterior to the base; walk posteriorly (+y) from it through the tissue.
          const Eigen::Vector3d start = e.base_centre_m + fu * e.lateral_m * e.lateral_axis +
                                        fv * e.si_m * Eigen::Vector3d::UnitZ() - 0.02 * Eigen::Vector3d::UnitY();
          const Eigen::Vector3d ijk = img.physicalToIndex(start);
          const int i = static_cast<int>(std::lround(ijk.x())), k = static_cast<int>(std::lround(ijk.z()));
          int j = static_cast<int>(std::lround(ijk.y()));
          if (!isTissueLabel(img.at(i, j, k))) continue;
          while (j + 1 < img.size.y() && isTissueLabel(img.at(i, j + 1, k))) ++j;
          ASSERT_LT(j + 1, img.size.y());
          EXPECT_EQ(img.at(i, j + 1, k), phantom_labels::kChestWall) << "column at u/a = " << fu << ", v/b = " << fv;
          ++columns;
        }
    }
    EXPECT_GE(columns, 10 * static_cast<int>(ph.prone_breasts.size()));
  }
}

TEST(Phantom, TwoBreastsOnACurvedWallAreSeparateAndSymmetric) {
  PhantomParams p = loadPhantomParams(configPath("phantom_two_breasts.yaml"));
  p.voxel_size_m = 2e-3;
  p.lesions = {};  // the case's lesions are not mirror images
  const Phantom ph = generatePhantom(p);
  ASSERT_EQ(ph.prone_breasts.size(), 2u);
  EXPECT_EQ(tissueComponents(ph.labels), 2);
  EXPECT_GT(ph.prone_breasts[0].base_centre_m.x(), 0.0);  // left first
  EXPECT_NEAR(ph.prone_breasts[0].volume(), ph.prone_breasts[1].volume(), 1e-12 * ph.prone_volume_m3);
  EXPECT_NEAR(ph.supine_breasts[0].volume(), ph.supine_breasts[1].volume(), 1e-12 * ph.prone_volume_m3);
  EXPECT_NEAR(ph.nipples_m[0].x(), -ph.nipples_m[1].x(), 1e-12);
  EXPECT_NEAR(ph.nipples_m[0].y(), ph.nipples_m[1].y(), 1e-12);
  long left = 0, right = 0;
  const LabelImage& img = ph.labels;
  for (int k = 0; k < img.size.z(); ++k)
    for (int j = 0; j < img.size.y(); ++j)
      for (int i = 0; i < img.size.x(); ++i)
        if (isTissueLabel(img.at(i, j, k))) (img.indexToPhysical(Eigen::Vector3d(i, j, k)).x() > 0 ? left : right)++;
  EXPECT_NEAR(static_cast<double>(left) / right, 1.0, 0.005);
  // The wall curves posteriorly away from the sternum, so each breast sits behind y = 0.
  EXPECT_GT(ph.prone_breasts[0].base_centre_m.y(), 0.0);
  EXPECT_NEAR(ph.chest_wall.surfaceY(0.0), 0.0, 1e-15);
}

TEST(Phantom, CurvedWallVolumeQuadratureAgreesWithBruteForceAndThePlanarLimit) {
  HalfEllipsoid e;
  e.lateral_m = 0.06;
  e.si_m = 0.05;
  e.depth_m = 0.04;
  const double half = 2.0 / 3.0 * kPi * e.lateral_m * e.si_m * e.depth_m;
  for (double R : {0.08, 0.15, 0.3}) {
    SCOPED_TRACE("R = " + std::to_string(R));
    const double phi = 0.3;
    e.wall_radius_m = R;
    e.base_centre_m = Eigen::Vector3d(R * std::sin(phi), R - R * std::cos(phi), 0.0);
    e.lateral_axis = Eigen::Vector3d(std::cos(phi), std::sin(phi), 0.0);
    e.depth_axis = Eigen::Vector3d(std::sin(phi), -std::cos(phi), 0.0);
    // Slow reference: midpoint rule over the ellipsoid's box in local coordinates (0.5 mm cells).
    const double h = 0.5e-3;
    long inside = 0;
    for (double u = -e.lateral_m + h / 2; u < e.lateral_m; u += h)
      for (double v = -e.si_m + h / 2; v < e.si_m; v += h)
        for (double w = -e.depth_m + h / 2; w < e.depth_m; w += h)
          inside += e.contains(e.base_centre_m + u * e.lateral_axis + v * Eigen::Vector3d::UnitZ() + w * e.depth_axis);
    EXPECT_NEAR(inside * h * h * h / e.volume(), 1.0, 2e-3);
    EXPECT_GT(e.volume(), half);  // the wall curves away, adding a sliver below the base plane
  }
  // Large radius: the sliver tends to ∫∫ u²/(2R) du dv over the base ellipse, i.e. a relative
  // excess of 3a²/(16·R·c).
  e.wall_radius_m = 1e4;
  const double first_order = 3.0 * e.lateral_m * e.lateral_m / (16.0 * e.wall_radius_m * e.depth_m);
  EXPECT_NEAR((e.volume() / half - 1.0) / first_order, 1.0, 1e-3);
  e.wall_radius_m = 0.0;
  EXPECT_DOUBLE_EQ(e.volume(), half);
}

TEST(Phantom, SkinLayerIsAShellUnderTheSurface) {
  PhantomParams p;
  p.voxel_size_m = 2e-3;
  p.skin_thickness_m = 4e-3;
  const Phantom ph = generatePhantom(p);
  const HalfEllipsoid& e = ph.prone_breasts[0];
  EXPECT_EQ(ph.analyticLabel(e.apex() - 2e-3 * e.depth_axis), phantom_labels::kSkin);
  EXPECT_NE(ph.analyticLabel(e.apex() - 6e-3 * e.depth_axis), phantom_labels::kSkin);
  EXPECT_EQ(ph.analyticLabel(e.base_centre_m + Eigen::Vector3d(0, -1e-3, 0)), phantom_labels::kGland);
  EXPECT_GT(countLabel(ph.labels, [](std::uint16_t l) { return l == phantom_labels::kSkin; }), 0);
}

TEST(Phantom, OtherTopLevelMapsAreIgnoredAndMissingKeysTakeDefaults) {
  const std::string path = writeCase("partial",
                                     "meshing: {target_elements: 1000}\n"
                                     "phantom:\n  depth_mm: 50\n  lesions: []\n"
                                     "simulation: {anything: [1, 2]}\n");
  const PhantomParams p = loadPhantomParams(path);
  EXPECT_DOUBLE_EQ(p.depth_m, 0.05);
  EXPECT_DOUBLE_EQ(p.lateral_semi_axis_m, PhantomParams().lateral_semi_axis_m);
  EXPECT_TRUE(p.lesions.empty());
}

TEST(Phantom, MalformedCasesGiveErrorsNamingTheFileKeyAndValue) {
  struct Bad {
    std::string name, yaml;
    std::vector<std::string> mentions;
  };
  const std::vector<Bad> cases = {
      {"unknown_key", "phantom:\n  depht_mm: 70\n", {"phantom.depht_mm", "70", "depth_mm"}},
      {"negative_size", "phantom:\n  lateral_semi_axis_mm: -60\n", {"lateral_semi_axis_mm", "-60", "positive"}},
      {"zero_voxel", "phantom:\n  voxel_size_mm: 0\n", {"voxel_size_mm", "0", "positive"}},
      {"wrong_type", "phantom:\n  depth_mm: deep\n", {"phantom.depth_mm", "deep", "number in mm"}},
      {"list_for_number", "phantom:\n  si_semi_axis_mm: [1, 2]\n", {"phantom.si_semi_axis_mm", "number"}},
      {"bad_enum", "phantom:\n  chest_wall_shape: round\n", {"chest_wall_shape", "round", "cylindrical"}},
      {"fractional_count", "phantom:\n  num_breasts: 1.5\n", {"num_breasts", "1.5"}},
      {"unknown_lesion_key",
       "phantom:\n  lesions:\n    - {name: a, position_mm: [0, -20, 0], radius: 3}\n",
       {"lesions[0].radius", "radius_mm"}},
      {"lesion_outside", "phantom:\n  lesions:\n    - {name: far, position_mm: [0, 20, 0]}\n",
       {"lesions[0].position_mm", "far", "inside"}},
      {"overlapping_breasts", "phantom:\n  num_breasts: 2\n  breast_separation_mm: 100\n  lesions: []\n",
       {"breast_separation_mm", "100", "overlap"}},
      {"no_phantom_map", "meshing: {target_elements: 1000}\n", {"phantom"}},
  };
  for (const Bad& c : cases) {
    SCOPED_TRACE(c.name);
    const std::string path = writeCase(c.name, c.yaml);
    const std::string msg = loadError(path);
    ASSERT_FALSE(msg.empty());
    EXPECT_NE(msg.find(path), std::string::npos) << msg;
    for (const std::string& m : c.mentions) EXPECT_NE(msg.find(m), std::string::npos) << "'" << m << "' not in: " << msg;
  }
  EXPECT_THROW(loadPhantomParams(::testing::TempDir() + "/no_such_phantom_case.yaml"), std::runtime_error);
}

TEST(Phantom, SupineSurfaceIsWrittenAsObjAndStl) {
  PhantomParams p;
  p.voxel_size_m = 3e-3;
  p.surface_edge_m = 5e-3;
  const Phantom ph = generatePhantom(p);
  const std::string obj = ::testing::TempDir() + "/phantom_supine.obj";
  const std::string stl = ::testing::TempDir() + "/phantom_supine.stl";
  writePhantomSurface(obj, ph.supine_surface);
  writePhantomSurface(stl, ph.supine_surface);
  std::ifstream in(obj);
  long v = 0, f = 0, groups = 0;
  for (std::string line; std::getline(in, line);) {
    v += line.rfind("v ", 0) == 0;
    f += line.rfind("f ", 0) == 0;
    groups += line.rfind("g ", 0) == 0;
  }
  EXPECT_EQ(v, ph.supine_surface.vertices_m.rows());
  EXPECT_EQ(f, ph.supine_surface.triangles.rows());
  EXPECT_EQ(groups, 2);
  std::ifstream in_stl(stl);
  long facets = 0;
  for (std::string line; std::getline(in_stl, line);) facets += line.find("facet normal") != std::string::npos;
  EXPECT_EQ(facets, ph.supine_surface.triangles.rows());
  EXPECT_THROW(writePhantomSurface(::testing::TempDir() + "/phantom.ply", ph.supine_surface), std::runtime_error);
}
