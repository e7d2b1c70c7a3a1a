#include "breast_sim/core/mri/supine_resampling.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Dense>

#include "breast_sim/core/mri/mri_volume.h"
#include "label_lookup.h"

namespace breast_sim::core {

namespace {

using Clock = std::chrono::steady_clock;

// Barycentric slack: a voxel centre on a shared face counts as inside both tetrahedra (the lower index
// takes it), so no voxel falls through the cracks between elements.
constexpr double kInside = 1e-9;

// A deformed tetrahedron ready for containment tests.
struct DeformedTet {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();   // deformed node 0 [m]
  Eigen::Matrix3d inverse = Eigen::Matrix3d::Zero();  // (y1 − y0, y2 − y0, y3 − y0)⁻¹
  Eigen::Vector3d lo, hi;                             // bounding box [m], slightly widened
  bool valid = false;                                 // false for a flat (zero-volume) element
};

// λ of x in t, the one expression both paths use (so they decide alike, bit for bit).
inline bool contains(const DeformedTet& t, const Eigen::Vector3d& x, Eigen::Vector4d& lambda) {
  const Eigen::Vector3d l = t.inverse * (x - t.origin);
  lambda << 1.0 - l.sum(), l;
  return lambda.minCoeff() >= -kInside;
}

std::vector<DeformedTet> deformedTets(const TetMesh& mesh, const Points& displacement) {
  const Tets& tets = mesh.tets();
  std::vector<DeformedTet> out(static_cast<std::size_t>(tets.rows()));
#pragma omp parallel for schedule(static)
  for (long t = 0; t < static_cast<long>(tets.rows()); ++t) {
    Eigen::Vector3d y[4];
    for (int a = 0; a < 4; ++a) y[a] = (mesh.nodes().row(tets(t, a)) + displacement.row(tets(t, a))).transpose();
    Eigen::Matrix3d m;
    m << y[1] - y[0], y[2] - y[0], y[3] - y[0];
    const double det = m.determinant();
    const double scale = std::max({m.col(0).squaredNorm(), m.col(1).squaredNorm(), m.col(2).squaredNorm()});
    DeformedTet& d = out[t];
    d.lo = d.hi = y[0];
    for (int a = 1; a < 4; ++a) d.lo = d.lo.cwiseMin(y[a]), d.hi = d.hi.cwiseMax(y[a]);
    const Eigen::Vector3d widen = Eigen::Vector3d::Constant(1e-6 * std::sqrt(scale) + 1e-12);
    d.lo -= widen;
    d.hi += widen;
    if (!(std::abs(det) > 1e-12 * std::pow(scale, 1.5))) continue;  // flat: holds no voxel centre
    d.origin = y[0];
    d.inverse = m.inverse();
    d.valid = true;
  }
  return out;
}

void checkInputs(const TetMesh& mesh, const Points& displacement, const ScalarImage* image, const LabelImage* labels,
                 const ImageGeometry& grid, const SupineResampleOptions& options) {
  options.validate();
  grid.validate();
  if (!image && !labels) throw std::invalid_argument("resampleToSupine: give a prone image, prone labels or both");
  if (displacement.rows() != mesh.numNodes())
    throw std::invalid_argument("resampleToSupine: " + std::to_string(displacement.rows()) + " displacements for " +
                                std::to_string(mesh.numNodes()) + " nodes");
  if (!displacement.allFinite()) throw std::invalid_argument("resampleToSupine: a displacement is not finite");
  if (image) {
    image->geometry.validate();
    if (static_cast<long>(image->values.size()) != image->geometry.numVoxels())
      throw std::invalid_argument("resampleToSupine: the prone image's value count does not match its grid");
  }
  if (labels) labels->validate();
  if (grid.numVoxels() > options.max_voxels)
    throw std::invalid_argument("resampleToSupine: the supine grid has " + std::to_string(grid.numVoxels()) +
                                " voxels, more than max_voxels = " + std::to_string(options.max_voxels));
}

// Writes voxel v of the outputs from tetrahedron t at barycentric λ.
struct Writer {
  const TetMesh& mesh;
  const ScalarImage* image;
  const LabelImage* labels;
  SupineImages& out;
  std::vector<std::uint8_t> wall;  // per label value: 1 for the chest wall (a table: set lookups per voxel cost)
  LabelImage none;
  LabelLookup label_at;

  Writer(const TetMesh& m, const ScalarImage* i, const LabelImage* l, SupineImages& o, const TissueLabels& map)
      : mesh(m), image(i), labels(l), out(o), wall(65536, 0), label_at(l ? *l : none) {
    for (std::uint16_t v : map.chest_wall) wall[v] = 1;
  }
  void body(long v, int t, const Eigen::Vector4d& lambda) const {
    Eigen::Vector3d x = Eigen::Vector3d::Zero();
    for (int a = 0; a < 4; ++a) x += lambda[a] * mesh.nodes().row(mesh.tets()(t, a)).transpose();
    if (image) out.image.values[v] = static_cast<float>(sampleTrilinear(*image, x));
    if (labels) out.labels.labels[v] = label_at(x);
  }
  // Outside the deformed body: the chest wall stays where it is; the rest is air.
  void outside(long v, const Eigen::Vector3d& y) const {
    if (!labels) return;
    const std::uint16_t l = label_at(y);
    if (!wall[l]) return;
    out.labels.labels[v] = l;
    if (image && insideGrid(image->geometry, y)) out.image.values[v] = static_cast<float>(sampleTrilinear(*image, y));
  }
};

SupineImages emptyOutputs(const ScalarImage* image, const LabelImage* labels, const ImageGeometry& grid,
                          const SupineResampleOptions& o) {
  SupineImages out;
  if (image) {
    out.image.geometry = grid;
    out.image.values.assign(static_cast<std::size_t>(grid.numVoxels()), o.air_value);
  }
  if (labels) {
    ScalarImage shape;
    shape.geometry = grid;
    out.labels = labelImageLike(shape, 0);
  }
  return out;
}

}  // namespace

void SupineResampleOptions::validate() const {
  if (!(margin_m >= 0) || !std::isfinite(margin_m) || margin_m > 1.0)
    throw std::invalid_argument("supine resampling margin_m = " + std::to_string(margin_m) + " is invalid: expected [0, 1] m");
  for (int a = 0; a < 3; ++a)
    if (!(spacing_m[a] >= 0) || !std::isfinite(spacing_m[a]) || spacing_m[a] > 0.05)
      throw std::invalid_argument("supine resampling spacing_m = " + std::to_string(spacing_m[a]) +
                                  " is invalid: expected 0 (the prone spacing) or (0, 0.05] m");
  if (!std::isfinite(air_value)) throw std::invalid_argument("supine resampling air_value is not finite");
  if (max_voxels < 1) throw std::invalid_argument("supine resampling max_voxels must be at least 1");
}

ImageGeometry supineGrid(const ImageGeometry& prone, const Points& deformed_m, const SupineResampleOptions& o) {
  o.validate();
  prone.validate();
  if (deformed_m.rows() == 0) throw std::invalid_argument("supineGrid: the deformed model has no nodes");
  if (!deformed_m.allFinite()) throw std::invalid_argument("supineGrid: a deformed node is not finite");
  ImageGeometry g;
  g.direction = prone.direction;
  for (int a = 0; a < 3; ++a) g.spacing_m[a] = o.spacing_m[a] > 0 ? o.spacing_m[a] : prone.spacing_m[a];
  // Node coordinates along the prone axes, relative to the prone origin [m].
  const Eigen::Matrix<double, Eigen::Dynamic, 3> q =
      (deformed_m.rowwise() - prone.origin_m.transpose()) * prone.direction;
  Eigen::Vector3i start;
  double voxels = 1.0;
  for (int a = 0; a < 3; ++a) {
    const double lo = q.col(a).minCoeff() - o.margin_m, hi = q.col(a).maxCoeff() + o.margin_m;
    start[a] = static_cast<int>(std::floor(lo / g.spacing_m[a]));
    const int end = static_cast<int>(std::ceil(hi / g.spacing_m[a]));
    g.size[a] = end - start[a] + 1;
    voxels *= g.size[a];
  }
  if (voxels > static_cast<double>(o.max_voxels)) {
    std::ostringstream s;
    s << "supineGrid: the deformed model's box needs " << g.size.transpose() << " voxels, more than max_voxels = "
      << o.max_voxels << "; use larger voxels (spacing_m) or a smaller margin";
    throw std::invalid_argument(s.str());
  }
  g.origin_m = prone.origin_m + prone.direction * (start.cast<double>().cwiseProduct(g.spacing_m));
  return g;
}

SupineImages resampleToSupine(const TetMesh& mesh, const Points& displacement, const ScalarImage* prone_image,
                              const LabelImage* prone_labels, const ImageGeometry& grid, const SupineResampleOptions& options) {
  const auto t0 = Clock::now();
  checkInputs(mesh, displacement, prone_image, prone_labels, grid, options);
  SupineImages out = emptyOutputs(prone_image, prone_labels, grid, options);
  const Writer writer(mesh, prone_image, prone_labels, out, options.label_map);
  const std::vector<DeformedTet> tets = deformedTets(mesh, displacement);
  // The voxel box of each tetrahedron, and per slice k the tetrahedra that reach it, in index order.
  const int nz = grid.size.z();
  std::vector<Eigen::Vector3i> box_lo(tets.size()), box_hi(tets.size());
  std::vector<std::vector<int>> slices(static_cast<std::size_t>(nz));
  for (std::size_t t = 0; t < tets.size(); ++t) {
    if (!tets[t].valid) continue;
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = Eigen::Vector3d::Constant(-1e300);
    for (int c = 0; c < 8; ++c) {
      const Eigen::Vector3d corner((c & 1) ? tets[t].hi.x() : tets[t].lo.x(), (c & 2) ? tets[t].hi.y() : tets[t].lo.y(),
                                   (c & 4) ? tets[t].hi.z() : tets[t].lo.z());
      const Eigen::Vector3d x = grid.physicalToIndex(corner);
      lo = lo.cwiseMin(x);
      hi = hi.cwiseMax(x);
    }
    box_lo[t] = lo.array().ceil().cast<int>().max(0);
    box_hi[t] = hi.array().floor().cast<int>().min(grid.size.array() - 1);
    if ((box_lo[t].array() > box_hi[t].array()).any()) continue;
    for (int k = box_lo[t].z(); k <= box_hi[t].z(); ++k) slices[k].push_back(static_cast<int>(t));
  }
  std::vector<std::uint8_t> done(static_cast<std::size_t>(grid.numVoxels()), 0);
  long body = 0;
  const Eigen::Vector3d step_i = grid.direction.col(0) * grid.spacing_m.x();
#pragma omp parallel for schedule(dynamic, 1) reduction(+ : body)
  for (int k = 0; k < nz; ++k) {
    for (int t : slices[k]) {
      const DeformedTet& d = tets[t];
      for (int j = box_lo[t].y(); j <= box_hi[t].y(); ++j) {
        // Along the row, λ is affine in i: the i where all four λ ≥ 0, widened by a voxel, is where
        // the exact test below can succeed.
        const Eigen::Vector3d a = d.inverse * (grid.indexToPhysical(Eigen::Vector3d(0, j, k)) - d.origin);
        const Eigen::Vector3d b = d.inverse * step_i;
        double lo = box_lo[t].x(), hi = box_hi[t].x();
        const double coef[4][2] = {{1.0 - a.sum(), -b.sum()}, {a.x(), b.x()}, {a.y(), b.y()}, {a.z(), b.z()}};
        for (const auto& c : coef) {  // c0 + c1 i ≥ 0
          if (std::abs(c[1]) < 1e-15) {
            if (c[0] < -1e-6) hi = lo - 1;
          } else if (c[1] > 0) {
            lo = std::max(lo, -c[0] / c[1]);
          } else {
            hi = std::min(hi, -c[0] / c[1]);
          }
        }
        if (hi < lo - 2) continue;
        const int i0 = std::max(box_lo[t].x(), static_cast<int>(std::floor(lo)) - 1);
        const int i1 = std::min(box_hi[t].x(), static_cast<int>(std::ceil(hi)) + 1);
        for (int i = i0; i <= i1; ++i) {
          const long v = grid.index(i, j, k);
          if (done[v]) continue;
          Eigen::Vector4d lambda;
          if (!contains(d, grid.indexToPhysical(Eigen::Vector3d(i, j, k)), lambda)) continue;
          done[v] = 1;
          ++body;
          writer.body(v, t, lambda);
        }
      }
    }
    for (int j = 0; j < grid.size.y(); ++j)
      for (int i = 0; i < grid.size.x(); ++i) {
        const long v = grid.index(i, j, k);
        if (!done[v]) writer.outside(v, grid.indexToPhysical(Eigen::Vector3d(i, j, k)));
      }
  }
  out.body_voxels = body;
  out.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
  return out;
}

SupineImages resampleToSupineReference(const TetMesh& mesh, const Points& displacement, const ScalarImage* prone_image,
                                       const LabelImage* prone_labels, const ImageGeometry& grid,
                                       const SupineResampleOptions& options) {
  const auto t0 = Clock::now();
  checkInputs(mesh, displacement, prone_image, prone_labels, grid, options);
  SupineImages out = emptyOutputs(prone_image, prone_labels, grid, options);
  const Writer writer(mesh, prone_image, prone_labels, out, options.label_map);
  const std::vector<DeformedTet> tets = deformedTets(mesh, displacement);
  long body = 0;
#pragma omp parallel for schedule(dynamic, 1) reduction(+ : body)
  for (int k = 0; k < grid.size.z(); ++k)
    for (int j = 0; j < grid.size.y(); ++j)
      for (int i = 0; i < grid.size.x(); ++i) {
        const long v = grid.index(i, j, k);
        const Eigen::Vector3d y = grid.indexToPhysical(Eigen::Vector3d(i, j, k));
        bool inside = false;
        for (std::size_t t = 0; t < tets.size() && !inside; ++t) {
          const DeformedTet& d = tets[t];
          if (!d.valid || (y.array() < d.lo.array()).any() || (y.array() > d.hi.array()).any()) continue;
          Eigen::Vector4d lambda;
          if (!contains(d, y, lambda)) continue;
          inside = true;
          ++body;
          writer.body(v, static_cast<int>(t), lambda);
        }
        if (!inside) writer.outside(v, y);
      }
  out.body_voxels = body;
  out.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
  return out;
}

}  // namespace breast_sim::core
