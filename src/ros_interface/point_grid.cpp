// Exact nearest-neighbour queries on a hashed uniform grid (see point_grid.h).
#include "breast_sim/ros_interface/point_grid.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace breast_sim::ros_interface {

namespace {

constexpr uint64_t kEmpty = ~uint64_t(0);
constexpr int64_t kMaxCells = (int64_t(1) << 21) - 2;  ///< per axis, so a key packs into 63 bits
/// Relative margin on distances compared with cell boundaries: a float squared distance differs from
/// the exact one by a few ulp (~1e-7 relative), so a cell is skipped only when it is farther by 1e-5.
constexpr double kMargin = 1e-5;

/// The 27 cell offsets of a 3×3×3 block, by increasing distance (own cell, faces, edges, corners).
constexpr int kNeighbourOffsets[27][3] = {
    {0, 0, 0},   {-1, 0, 0},  {1, 0, 0},   {0, -1, 0},  {0, 1, 0},   {0, 0, -1},  {0, 0, 1},
    {-1, -1, 0}, {1, -1, 0},  {-1, 1, 0},  {1, 1, 0},   {-1, 0, -1}, {1, 0, -1},  {-1, 0, 1},
    {1, 0, 1},   {0, -1, -1}, {0, 1, -1},  {0, -1, 1},  {0, 1, 1},   {-1, -1, -1}, {1, -1, -1},
    {-1, 1, -1}, {1, 1, -1},  {-1, -1, 1}, {1, -1, 1},  {-1, 1, 1},  {1, 1, 1}};

uint64_t packKey(int64_t i, int64_t j, int64_t k) {
  return static_cast<uint64_t>(i) | (static_cast<uint64_t>(j) << 21) | (static_cast<uint64_t>(k) << 42);
}

}  // namespace

std::vector<Eigen::Vector3f> toFloat(const core::Points& p) {
  std::vector<Eigen::Vector3f> out(static_cast<size_t>(p.rows()));
  for (Eigen::Index i = 0; i < p.rows(); ++i)
    out[static_cast<size_t>(i)] = Eigen::Vector3f(static_cast<float>(p(i, 0)), static_cast<float>(p(i, 1)),
                                                  static_cast<float>(p(i, 2)));
  return out;
}

PointGrid::PointGrid(const core::Points& points_m, double cell_m) : points_(toFloat(points_m)) { build(cell_m); }

PointGrid::PointGrid(std::vector<Eigen::Vector3f> points_m, double cell_m) : points_(std::move(points_m)) {
  build(cell_m);
}

int64_t PointGrid::cellOf(float v, int a) const {
  return static_cast<int64_t>(std::floor((static_cast<double>(v) - origin_[a]) * inv_cell_));
}

void PointGrid::build(double cell_m) {
  if (!(cell_m > 0) || !std::isfinite(cell_m))
    throw std::invalid_argument("PointGrid: cell size " + std::to_string(cell_m) +
                                " m is not positive; pass about the distance the queries reach");
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  finite_ = 0;
  for (const auto& p : points_) {
    if (!p.allFinite()) continue;
    ++finite_;
    lo = lo.cwiseMin(p.cast<double>());
    hi = hi.cwiseMax(p.cast<double>());
  }
  cell_ = cell_m;
  if (finite_ == 0) {
    inv_cell_ = 1.0 / cell_;
    return;
  }
  while (((hi - lo) / cell_).maxCoeff() >= static_cast<double>(kMaxCells)) cell_ *= 2;
  inv_cell_ = 1.0 / cell_;
  origin_ = lo;
  for (int a = 0; a < 3; ++a) extent_[a] = cellOf(static_cast<float>(hi[a]), a) + 1;
  // hi is a float value, so cellOf(hi) is the cell of the extreme point itself.

  size_t slots = 16;
  while (slots < 2 * static_cast<size_t>(finite_)) slots *= 2;
  table_.assign(slots, Slot{kEmpty, 0, 0});
  mask_ = slots - 1;
  shift_ = 64;
  for (size_t s = slots; s > 1; s >>= 1) --shift_;
  std::vector<uint32_t> slot_of(points_.size(), UINT32_MAX);
  for (size_t n = 0; n < points_.size(); ++n) {
    const Eigen::Vector3f& p = points_[n];
    if (!p.allFinite()) continue;
    const uint64_t key = packKey(cellOf(p.x(), 0), cellOf(p.y(), 1), cellOf(p.z(), 2));
    uint64_t h = (key * 0x9E3779B97F4A7C15ull) >> shift_;
    while (table_[h].key != kEmpty && table_[h].key != key) h = (h + 1) & mask_;
    if (table_[h].key == kEmpty) table_[h].key = key;
    ++table_[h].end;  // count for now
    slot_of[n] = static_cast<uint32_t>(h);
  }
  uint32_t offset = 0;
  for (Slot& s : table_) {
    if (s.key == kEmpty) continue;
    s.begin = offset;
    offset += s.end;
    s.end = s.begin;  // fill pointer
  }
  sorted_.resize(static_cast<size_t>(finite_));
  sorted_index_.resize(static_cast<size_t>(finite_));
  for (size_t n = 0; n < points_.size(); ++n) {
    if (slot_of[n] == UINT32_MAX) continue;
    Slot& s = table_[slot_of[n]];
    sorted_[s.end] = points_[n];
    sorted_index_[s.end] = static_cast<int>(n);
    ++s.end;
  }
}

inline const PointGrid::Slot* PointGrid::find(int64_t i, int64_t j, int64_t k) const {
  const uint64_t key = packKey(i, j, k);
  uint64_t h = (key * 0x9E3779B97F4A7C15ull) >> shift_;
  while (true) {
    const Slot& s = table_[h];
    if (s.key == key) return &s;
    if (s.key == kEmpty) return nullptr;
    h = (h + 1) & mask_;
  }
}

template <typename Visit>
bool PointGrid::visitBox(const Eigen::Vector3f& q, double radius, Visit&& visit) const {
  if (finite_ == 0) return true;
  const double reach = radius * (1 + kMargin) + 1e-12;
  int64_t lo[3], hi[3];
  for (int a = 0; a < 3; ++a) {
    const double flo = std::floor((q[a] - reach - origin_[a]) * inv_cell_);
    const double fhi = std::floor((q[a] + reach - origin_[a]) * inv_cell_);
    if (!(fhi >= 0 && flo <= static_cast<double>(extent_[a] - 1))) return true;  // also a NaN query
    lo[a] = static_cast<int64_t>(std::max(0.0, flo));
    hi[a] = static_cast<int64_t>(std::min(static_cast<double>(extent_[a] - 1), fhi));
  }
  // A box of more cells than there are points (a huge radius, or a sparse far-flung cloud): every point.
  const double cells = static_cast<double>(hi[0] - lo[0] + 1) * static_cast<double>(hi[1] - lo[1] + 1) *
                       static_cast<double>(hi[2] - lo[2] + 1);
  if (cells > static_cast<double>(finite_)) {
    for (size_t m = 0; m < sorted_.size(); ++m)
      if (!visit(sorted_index_[m], sorted_[m])) return false;
    return true;
  }
  for (int64_t k = lo[2]; k <= hi[2]; ++k)
    for (int64_t j = lo[1]; j <= hi[1]; ++j)
      for (int64_t i = lo[0]; i <= hi[0]; ++i) {
        const Slot* s = find(i, j, k);
        if (!s) continue;
        for (uint32_t m = s->begin; m < s->end; ++m)
          if (!visit(sorted_index_[m], sorted_[m])) return false;
      }
  return true;
}

int PointGrid::nearestWithin(const Eigen::Vector3f& q, double radius_m, float* d2) const {
  const double r2 = radius_m * radius_m;
  int best = -1;
  float best_d2 = 0;
  visitBox(q, radius_m, [&](int index, const Eigen::Vector3f& p) {
    const float d = squaredDistanceF(q, p);
    if (static_cast<double>(d) <= r2 && (best < 0 || d < best_d2)) {
      best = index;
      best_d2 = d;
    }
    return true;
  });
  if (d2) *d2 = best_d2;
  return best;
}

bool PointGrid::anyWithin(const Eigen::Vector3f& q, double radius_m) const {
  const double r2 = radius_m * radius_m;
  return !visitBox(q, radius_m, [&](int, const Eigen::Vector3f& p) {
    return !(static_cast<double>(squaredDistanceF(q, p)) <= r2);
  });
}

int PointGrid::nearestK(const Eigen::Vector3f& q, int k, int* index, float* d2, double max_d2) const {
  if (k <= 0 || finite_ == 0) return 0;
  int n = 0;
  auto offer = [&](int i, float d) {
    if (!(static_cast<double>(d) <= max_d2)) return;
    if (n == k) {
      if (!(d < d2[k - 1])) return;  // as FLANN: a tie with the current k-th is not taken
      --n;
    }
    int m = n++;
    for (; m > 0 && d2[m - 1] > d; --m) {
      d2[m] = d2[m - 1];
      index[m] = index[m - 1];
    }
    d2[m] = d;
    index[m] = i;
  };
  if (!q.allFinite()) return 0;
  int64_t c[3], start = 0;
  for (int a = 0; a < 3; ++a) {
    const double ca = std::floor((q[a] - origin_[a]) * inv_cell_);
    if (std::abs(ca) > 1e12) {
      // Absurdly far from every point (beyond the rings' integer range): look at all of them.
      for (size_t m = 0; m < sorted_.size(); ++m) offer(sorted_index_[m], squaredDistanceF(q, sorted_[m]));
      return n;
    }
    c[a] = static_cast<int64_t>(ca);
    // Rings closer than the occupied cells are empty: start at the first one that reaches them.
    start = std::max(start, std::max(-c[a], c[a] - (extent_[a] - 1)));
  }
  // Cells of the block of rings 0..r that lie in the occupied range.
  auto blockCells = [&](int64_t r) {
    if (r < 0) return 0.0;
    double cells = 1;
    for (int a = 0; a < 3; ++a)
      cells *= static_cast<double>(std::max<int64_t>(0, std::min(c[a] + r, extent_[a] - 1) - std::max<int64_t>(c[a] - r, 0) + 1));
    return cells;
  };
  for (int64_t r = start;; ++r) {
    if (blockCells(r) - blockCells(r - 1) > static_cast<double>(finite_)) {
      // The next ring has more cells than there are points (a query in a sparse, far-flung region):
      // every point instead, from scratch.
      n = 0;
      for (size_t m = 0; m < sorted_.size(); ++m) offer(sorted_index_[m], squaredDistanceF(q, sorted_[m]));
      break;
    }
    const int64_t zlo = std::max<int64_t>(c[2] - r, 0), zhi = std::min<int64_t>(c[2] + r, extent_[2] - 1);
    const int64_t ylo = std::max<int64_t>(c[1] - r, 0), yhi = std::min<int64_t>(c[1] + r, extent_[1] - 1);
    const int64_t xlo = std::max<int64_t>(c[0] - r, 0), xhi = std::min<int64_t>(c[0] + r, extent_[0] - 1);
    auto cell = [&](int64_t i, int64_t j, int64_t kk) {
      const Slot* s = find(i, j, kk);
      if (!s) return;
      for (uint32_t m = s->begin; m < s->end; ++m) offer(sorted_index_[m], squaredDistanceF(q, sorted_[m]));
    };
    for (int64_t z = zlo; z <= zhi; ++z) {
      const bool zshell = z == c[2] - r || z == c[2] + r;
      for (int64_t y = ylo; y <= yhi; ++y) {
        if (zshell || y == c[1] - r || y == c[1] + r) {
          for (int64_t x = xlo; x <= xhi; ++x) cell(x, y, z);
        } else {
          if (c[0] - r >= 0 && c[0] - r < extent_[0]) cell(c[0] - r, y, z);
          if (r > 0 && c[0] + r >= 0 && c[0] + r < extent_[0]) cell(c[0] + r, y, z);
        }
      }
    }
    // Every occupied cell visited?
    bool all = true;
    for (int a = 0; a < 3; ++a) all = all && c[a] - r <= 0 && c[a] + r >= extent_[a] - 1;
    if (all) break;
    // Unvisited points lie outside the block of rings 0..r: at least `bound` from q.
    double bound = std::numeric_limits<double>::infinity();
    for (int a = 0; a < 3; ++a) {
      const double qa = q[a];
      bound = std::min(bound, qa - (origin_[a] + static_cast<double>(c[a] - r) * cell_));
      bound = std::min(bound, origin_[a] + static_cast<double>(c[a] + r + 1) * cell_ - qa);
    }
    if (bound > 0) {
      const double b2 = bound * bound * (1 - kMargin);
      if (b2 > max_d2) break;
      if (n == k && static_cast<double>(d2[k - 1]) < b2) break;
    }
  }
  return n;
}

void PointGrid::selfNearestK(int k, float* d2, int* found) const {
  std::fill(found, found + points_.size(), 0);
  if (k <= 0 || finite_ == 0) return;
  constexpr uint64_t kAxis = (uint64_t(1) << 21) - 1;
  // Cell by cell in parallel: each point's answer is written by the thread of its cell alone, so the
  // result does not depend on the thread count.
  const long slots = static_cast<long>(table_.size());
#pragma omp parallel if (points_.size() > 2048)
  {
    std::vector<float> bx, by, bz, dist;
    std::vector<int> scratch(static_cast<size_t>(k));
#pragma omp for schedule(dynamic, 64)
    for (long t = 0; t < slots; ++t) {
      const Slot& slot = table_[static_cast<size_t>(t)];
      if (slot.key == kEmpty) continue;
      const int64_t c[3] = {static_cast<int64_t>(slot.key & kAxis), static_cast<int64_t>((slot.key >> 21) & kAxis),
                            static_cast<int64_t>(slot.key >> 42)};
      // The points of the 27 cells around this one, coordinates apart (the distance loop vectorizes),
      // nearest cells first (own, faces, edges, corners) so that the k best fill early and most later
      // candidates are refused by one comparison.
      bx.clear();
      by.clear();
      bz.clear();
      for (const auto& o : kNeighbourOffsets) {
        const int64_t x = c[0] + o[0], y = c[1] + o[1], z = c[2] + o[2];
        if (x < 0 || y < 0 || z < 0 || x >= extent_[0] || y >= extent_[1] || z >= extent_[2]) continue;
        const Slot* s = find(x, y, z);
        if (!s) continue;
        for (uint32_t m = s->begin; m < s->end; ++m) {
          bx.push_back(sorted_[m].x());
          by.push_back(sorted_[m].y());
          bz.push_back(sorted_[m].z());
        }
      }
      const size_t nb = bx.size();
      dist.resize(nb);
      bool all = true;  // the 27 cells are every occupied cell
      for (int a = 0; a < 3; ++a) all = all && c[a] - 1 <= 0 && c[a] + 1 >= extent_[a] - 1;
      for (uint32_t m = slot.begin; m < slot.end; ++m) {
        const float qx = sorted_[m].x(), qy = sorted_[m].y(), qz = sorted_[m].z();
        for (size_t b = 0; b < nb; ++b) {
          // squaredDistanceF(q, b), written out so that it vectorizes (same operations per lane).
          const float dx = qx - bx[b], dy = qy - by[b], dz = qz - bz[b];
          float r = dx * dx;
          r += dy * dy;
          r += dz * dz;
          dist[b] = r;
        }
        const int index = sorted_index_[m];
        float* out = d2 + static_cast<size_t>(index) * static_cast<size_t>(k);
        int n = 0;
        for (size_t b = 0; b < nb; ++b) {
          const float d = dist[b];
          if (n == k) {
            if (!(d < out[k - 1])) continue;
            --n;
          }
          int j = n++;
          for (; j > 0 && out[j - 1] > d; --j) out[j] = out[j - 1];
          out[j] = d;
        }
        // Points outside the 27 cells are at least `bound` away.
        double bound = std::numeric_limits<double>::infinity();
        const Eigen::Vector3f& q = sorted_[m];
        for (int a = 0; a < 3; ++a) {
          bound = std::min(bound, q[a] - (origin_[a] + static_cast<double>(c[a] - 1) * cell_));
          bound = std::min(bound, origin_[a] + static_cast<double>(c[a] + 2) * cell_ - q[a]);
        }
        if (all || (n == k && bound > 0 && static_cast<double>(out[k - 1]) < bound * bound * (1 - kMargin))) {
          found[index] = n;
        } else {
          found[index] = nearestK(q, k, scratch.data(), out);
        }
      }
    }
  }
}

}  // namespace breast_sim::ros_interface
