#include "breast_sim/core/solver/multigrid.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <sstream>
#include <stdexcept>

#include <omp.h>

#include <Eigen/Dense>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/point_embedding.h"
#include "breast_sim/core/solver/block_kernels.h"

namespace breast_sim::core {

namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// Levels below this many nodes run on one thread: waking the second costs more than it saves.
constexpr int kParallelMinNodes = 400;

double meanBoundaryEdge(const TetMesh& mesh) {
  const Triangles& f = mesh.boundary().triangles;
  if (f.rows() == 0) return 0.0;
  const Points& x = mesh.nodes();
  double sum = 0.0;
  for (Eigen::Index t = 0; t < f.rows(); ++t)
    for (int e = 0; e < 3; ++e) sum += (x.row(f(t, e)) - x.row(f(t, (e + 1) % 3))).norm();
  return sum / (3.0 * static_cast<double>(f.rows()));
}

// Checks the 3×3-block layout of fem/block_pattern.h and returns the neighbour lists
// (block columns) of every node: start (N + 1) and node indices.
void blockGraph(const SparseMatrix& A, const std::string& who, std::vector<int>& start, std::vector<int>& nbr,
                std::vector<int>* diag_block) {
  auto fail = [&](const std::string& what) {
    throw std::invalid_argument(who + ": the matrix is not in 3×3-block layout (fem/block_pattern.h): " + what);
  };
  if (A.rows() != A.cols() || A.rows() % 3 != 0) fail("size " + std::to_string(A.rows()) + "×" + std::to_string(A.cols()));
  if (!A.isCompressed()) fail("it is not compressed (call makeCompressed())");
  const int n = static_cast<int>(A.rows() / 3);
  const int* outer = A.outerIndexPtr();
  const int* inner = A.innerIndexPtr();
  start.assign(static_cast<size_t>(n) + 1, 0);
  nbr.clear();
  nbr.reserve(static_cast<size_t>(A.nonZeros() / 9));
  if (diag_block) diag_block->assign(static_cast<size_t>(n), -1);
  for (int i = 0; i < n; ++i) {
    const int len = outer[3 * i + 1] - outer[3 * i];
    if (len % 3 != 0 || outer[3 * i + 2] - outer[3 * i + 1] != len || outer[3 * i + 3] - outer[3 * i + 2] != len)
      fail("rows of node " + std::to_string(i) + " differ in length or are not whole blocks");
    int last = -1;
    for (int k = 0; k < len / 3; ++k) {
      const int c0 = inner[outer[3 * i] + 3 * k];
      if (c0 % 3 != 0 || c0 / 3 <= last) fail("block " + std::to_string(k) + " of node " + std::to_string(i));
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
          if (inner[outer[3 * i + r] + 3 * k + c] != c0 + c)
            fail("block " + std::to_string(k) + " of node " + std::to_string(i) + ", row " + std::to_string(r));
      last = c0 / 3;
      if (last == i && diag_block) (*diag_block)[i] = k;
      nbr.push_back(last);
    }
    if (diag_block && (*diag_block)[i] < 0) fail("node " + std::to_string(i) + " has no diagonal block");
    start[i + 1] = static_cast<int>(nbr.size());
  }
}

}  // namespace

// ---------------------------------------------------------------------------------------------------
// Prolongation and hierarchy

NodeProlongation barycentricProlongation(const TetMesh& fine, const TetMesh& coarse, double snap_tolerance_m,
                                         std::vector<double>* outside_distance_m) {
  const std::vector<bool> used = fine.usedNodes();
  std::vector<int> ids;
  for (int i = 0; i < fine.numNodes(); ++i)
    if (used[i]) ids.push_back(i);
  Points q(static_cast<Eigen::Index>(ids.size()), 3);
  std::vector<std::string> names;
  names.reserve(ids.size());
  for (size_t k = 0; k < ids.size(); ++k) {
    q.row(static_cast<Eigen::Index>(k)) = fine.nodes().row(ids[k]);
    names.push_back("fine node " + std::to_string(ids[k]));
  }
  const PointEmbedding embedding(coarse, q, names, snap_tolerance_m);

  if (outside_distance_m) outside_distance_m->assign(static_cast<size_t>(fine.numNodes()), 0.0);
  std::vector<Eigen::Triplet<double, int>> entries;
  entries.reserve(4 * ids.size());
  for (size_t k = 0; k < ids.size(); ++k) {
    const EmbeddedPoint& e = embedding.points()[k];
    Eigen::Vector4d w = e.weights;
    for (int v = 0; v < 4; ++v)
      if (w[v] < 1e-12) w[v] = 0.0;
    w /= w.sum();
    for (int v = 0; v < 4; ++v)
      if (w[v] > 0.0) entries.emplace_back(ids[k], coarse.tets()(e.tet, v), w[v]);
    if (outside_distance_m) (*outside_distance_m)[ids[k]] = e.outside_distance_m;
  }
  NodeProlongation P(fine.numNodes(), coarse.numNodes());
  P.setFromTriplets(entries.begin(), entries.end());
  P.makeCompressed();
  return P;
}

SparseMatrix expandToDofs(const NodeProlongation& P) {
  std::vector<Eigen::Triplet<double, int>> entries;
  entries.reserve(3 * static_cast<size_t>(P.nonZeros()));
  for (int i = 0; i < P.outerSize(); ++i)
    for (NodeProlongation::InnerIterator it(P, i); it; ++it)
      for (int a = 0; a < 3; ++a) entries.emplace_back(3 * i + a, 3 * static_cast<int>(it.col()) + a, it.value());
  SparseMatrix out(3 * P.rows(), 3 * P.cols());
  out.setFromTriplets(entries.begin(), entries.end());
  return out;
}

MeshHierarchy::MeshHierarchy(std::vector<TetMesh> meshes, double snap_factor) : meshes_(std::move(meshes)) {
  if (meshes_.empty()) throw std::invalid_argument("MeshHierarchy: no mesh given (the fine mesh comes first)");
  for (size_t l = 1; l < meshes_.size(); ++l) meshes_[l] = mortonOrdered(meshes_[l]);
  for (size_t l = 0; l + 1 < meshes_.size(); ++l) {
    const double tol = snap_factor * meanBoundaryEdge(meshes_[l + 1]);
    std::vector<double> outside;
    try {
      prolongations_.push_back(barycentricProlongation(meshes_[l], meshes_[l + 1], tol, &outside));
    } catch (const std::invalid_argument& e) {
      std::ostringstream s;
      s << "MeshHierarchy: level " << l << " (" << meshes_[l].numTets() << " tetrahedra) does not fit in level "
        << l + 1 << " (" << meshes_[l + 1].numTets() << " tetrahedra, snap tolerance " << tol * 1e3
        << " mm): " << e.what() << "; mesh the coarse level finer or raise the snap factor";
      throw std::invalid_argument(s.str());
    }
    outside_distance_m_.push_back(std::move(outside));
  }
}

std::vector<TetMesh> buildCoarseMeshes(const ModelCase& model_case, const SimulationModel& fine,
                                       const CoarseningOptions& options) {
  if (!(options.size_factor > 1.0))
    throw std::invalid_argument("buildCoarseMeshes: size_factor = " + std::to_string(options.size_factor) +
                                " must be > 1");
  if (!(fine.meshing.interior_size_m > 0.0))
    throw std::invalid_argument("buildCoarseMeshes: the fine model has no interior size in its meshing report; "
                                "build it with buildSimulationModel()");
  std::vector<RefinementPoint> refine;
  for (const auto& l : model_case.lesions) refine.push_back({l.position_m, l.radius_m});
  MeshingOptions m = model_case.meshing;
  m.target_elements = 0;
  std::vector<TetMesh> out;
  int previous = fine.mesh.numTets();
  double size = fine.meshing.interior_size_m;
  for (int level = 1; level <= options.max_coarse_levels && previous > options.max_coarsest_elements; ++level) {
    size *= options.size_factor;
    m.interior_size_m = size;
    TetMesh mesh;
    try {
      mesh = meshLabelImage(model_case.image, model_case.labels, refine, m);
    } catch (const std::exception& e) {
      std::ostringstream s;
      s << "buildCoarseMeshes: case '" << model_case.name << "', level " << level << " at interior size "
        << size * 1e3 << " mm: " << e.what();
      throw std::runtime_error(s.str());
    }
    if (mesh.numTets() > 0.8 * previous) break;  // the surface bounds the size: no real coarsening left
    previous = mesh.numTets();
    out.push_back(std::move(mesh));
  }
  return out;
}

MeshHierarchy buildMeshHierarchy(const ModelCase& model_case, const SimulationModel& fine,
                                 const CoarseningOptions& options, double snap_factor) {
  std::vector<TetMesh> meshes = buildCoarseMeshes(model_case, fine, options);
  meshes.insert(meshes.begin(), fine.mesh);
  return MeshHierarchy(std::move(meshes), snap_factor);
}

// ---------------------------------------------------------------------------------------------------
// Galerkin product [GW10]: A_c row I = Σ_{i child of I} w_iI · (row i of A) · P. Each coarse row is
// one task: the rows of A of its children are summed into a small dense buffer over the fine nodes
// they touch (C = Pᵀ A restricted to row I), which is then multiplied by P into A_c's row I. No
// intermediate matrix is stored and no two tasks write the same memory.

void GalerkinProduct::analyze(const SparseMatrix& A, const NodeProlongation& P) {
  const std::string who = "GalerkinProduct";
  if (A.rows() != 3 * P.rows()) {
    std::ostringstream s;
    s << who << ": the matrix has " << A.rows() << " rows, the prolongation " << P.rows() << " fine nodes (×3 = "
      << 3 * P.rows() << ")";
    throw std::invalid_argument(s.str());
  }
  std::vector<int> nbr_start, nbr;
  blockGraph(A, who, nbr_start, nbr, nullptr);
  P_ = P;
  P_.makeCompressed();
  const int nf = static_cast<int>(P_.rows()), nc = static_cast<int>(P_.cols());
  const int* pout = P_.outerIndexPtr();
  const int* pin = P_.innerIndexPtr();
  const double* pval = P_.valuePtr();

  // Pᵀ: children of every coarse node.
  child_start_.assign(static_cast<size_t>(nc) + 1, 0);
  for (int k = 0; k < P_.nonZeros(); ++k) ++child_start_[pin[k] + 1];
  for (int I = 0; I < nc; ++I) child_start_[I + 1] += child_start_[I];
  child_.resize(static_cast<size_t>(P_.nonZeros()));
  child_weight_.resize(child_.size());
  {
    std::vector<int> fill(child_start_.begin(), child_start_.end() - 1);
    for (int i = 0; i < nf; ++i)
      for (int k = pout[i]; k < pout[i + 1]; ++k) {
        child_[fill[pin[k]]] = i;
        child_weight_[fill[pin[k]]++] = pval[k];
      }
  }

  fine_start_.assign(1, 0);
  fine_.clear();
  c_start_.assign(1, 0);
  c_slot_.clear();
  g_count_.clear();
  g_start_.assign(1, 0);
  g_weight_.clear();
  g_slot_.clear();
  diag_k_.assign(static_cast<size_t>(nc), 0);
  std::vector<int> fine_stamp(static_cast<size_t>(nf), -1), fine_local(static_cast<size_t>(nf), 0);
  std::vector<int> coarse_stamp(static_cast<size_t>(nc), -1), coarse_local(static_cast<size_t>(nc), 0);
  std::vector<int> cols, G;
  std::vector<int> coarse_start(1, 0), coarse_cols;  // block pattern of A_c
  max_fine_ = 0;
  for (int I = 0; I < nc; ++I) {
    // F(I): the fine nodes coupled to I's children, ascending.
    cols.clear();
    for (int ch = child_start_[I]; ch < child_start_[I + 1]; ++ch)
      for (int k = nbr_start[child_[ch]]; k < nbr_start[child_[ch] + 1]; ++k)
        if (fine_stamp[nbr[k]] != I) {
          fine_stamp[nbr[k]] = I;
          cols.push_back(nbr[k]);
        }
    std::sort(cols.begin(), cols.end());
    for (size_t s = 0; s < cols.size(); ++s) fine_local[cols[s]] = static_cast<int>(s);
    fine_.insert(fine_.end(), cols.begin(), cols.end());
    fine_start_.push_back(static_cast<int>(fine_.size()));
    max_fine_ = std::max(max_fine_, static_cast<int>(cols.size()));
    for (int ch = child_start_[I]; ch < child_start_[I + 1]; ++ch)
      for (int k = nbr_start[child_[ch]]; k < nbr_start[child_[ch] + 1]; ++k) c_slot_.push_back(fine_local[nbr[k]]);
    c_start_.push_back(static_cast<int>(c_slot_.size()));
    // G(I): the coarse parents of F(I), ascending = the block columns of A_c's row I.
    G.clear();
    for (int f : cols)
      for (int k = pout[f]; k < pout[f + 1]; ++k)
        if (coarse_stamp[pin[k]] != I) {
          coarse_stamp[pin[k]] = I;
          G.push_back(pin[k]);
        }
    if (coarse_stamp[I] != I) G.push_back(I);  // keep a diagonal block even for a node without children
    std::sort(G.begin(), G.end());
    for (size_t s = 0; s < G.size(); ++s) coarse_local[G[s]] = static_cast<int>(s);
    diag_k_[I] = coarse_local[I];
    for (int f : cols) {
      int count = 0;
      for (int k = pout[f]; k < pout[f + 1]; ++k)
        if (pin[k] >= I) {
          g_weight_.push_back(k);
          g_slot_.push_back(coarse_local[pin[k]]);
          ++count;
        }
      g_count_.push_back(static_cast<unsigned char>(count));
    }
    g_start_.push_back(static_cast<int>(g_slot_.size()));
    coarse_cols.insert(coarse_cols.end(), G.begin(), G.end());
    coarse_start.push_back(static_cast<int>(coarse_cols.size()));
  }

  // A_c in block layout: rows 3I + r hold columns 3J + c for J in G(I).
  coarse_ = SparseMatrix(3 * nc, 3 * nc);
  coarse_.resizeNonZeros(9 * static_cast<Eigen::Index>(coarse_cols.size()));
  int* cout = coarse_.outerIndexPtr();
  int* cin = coarse_.innerIndexPtr();
  cout[0] = 0;
  for (int I = 0; I < nc; ++I) {
    const int len = 3 * (coarse_start[I + 1] - coarse_start[I]);
    for (int r = 0; r < 3; ++r) {
      int* row = cin + cout[3 * I + r];
      for (int k = coarse_start[I]; k < coarse_start[I + 1]; ++k)
        for (int c = 0; c < 3; ++c) *row++ = 3 * coarse_cols[k] + c;
      cout[3 * I + r + 1] = cout[3 * I + r] + len;
    }
  }
  std::fill(coarse_.valuePtr(), coarse_.valuePtr() + coarse_.nonZeros(), 0.0);
  // Lower blocks (I, J < I) are copies of the transposed upper blocks (J, I).
  mirror_start_.assign(1, 0);
  mirror_dst_.clear();
  mirror_node_.clear();
  mirror_k_.clear();
  for (int I = 0; I < nc; ++I) {
    for (int k = coarse_start[I]; k < coarse_start[I] + diag_k_[I]; ++k) {
      const int J = coarse_cols[k];
      const auto first = coarse_cols.begin() + coarse_start[J], last = coarse_cols.begin() + coarse_start[J + 1];
      mirror_dst_.push_back(k - coarse_start[I]);
      mirror_node_.push_back(J);
      mirror_k_.push_back(static_cast<int>(std::lower_bound(first, last, I) - first));
    }
    mirror_start_.push_back(static_cast<int>(mirror_dst_.size()));
  }

  buffers_.assign(static_cast<size_t>(std::max(1, omp_get_max_threads())),
                  std::vector<double>(9 * static_cast<size_t>(std::max(max_fine_, 1))));
  fine_rows_ = A.rows();
  fine_nnz_ = A.nonZeros();
}

void GalerkinProduct::compute(const SparseMatrix& A, const double* free) {
  if (A.rows() != fine_rows_ || A.nonZeros() != fine_nnz_)
    throw std::logic_error("GalerkinProduct: compute() with a matrix of another pattern than analyze()");
  const int nc = static_cast<int>(P_.cols());
  const int* aout = A.outerIndexPtr();
  const double* aval = A.valuePtr();
  const double* pval = P_.valuePtr();
  const int* cout = coarse_.outerIndexPtr();
  double* cval = coarse_.valuePtr();
  const int threads = static_cast<int>(buffers_.size());
#pragma omp parallel num_threads(threads) if (P_.rows() > kParallelMinNodes)
  {
    double* C = buffers_[omp_get_thread_num()].data();
#pragma omp for schedule(dynamic, 32)
    for (int I = 0; I < nc; ++I) {
      // C = row I of (D P)ᵀ A over the fine nodes F(I).
      const int nF = fine_start_[I + 1] - fine_start_[I];
      std::fill(C, C + 9 * nF, 0.0);
      int idx = c_start_[I];
      for (int ch = child_start_[I]; ch < child_start_[I + 1]; ++ch) {
        const int i = child_[ch];
        const double w = child_weight_[ch];
        if (ch + 1 < child_start_[I + 1]) {
          // Children are scattered over A: fetch the next one's rows while this one is summed.
          const int next = 3 * child_[ch + 1];
          for (int r = 0; r < 3; ++r) {
            const double* row = aval + aout[next + r];
            __builtin_prefetch(row);
            __builtin_prefetch(row + 8);
            __builtin_prefetch(row + 16);
            __builtin_prefetch(row + 24);
            __builtin_prefetch(row + 32);
          }
        }
        const double m0 = free ? w * free[3 * i] : w;
        const double m1 = free ? w * free[3 * i + 1] : w;
        const double m2 = free ? w * free[3 * i + 2] : w;
        const double* a0 = aval + aout[3 * i];
        const double* a1 = aval + aout[3 * i + 1];
        const double* a2 = aval + aout[3 * i + 2];
        const int nb = (aout[3 * i + 1] - aout[3 * i]) / 3;
        if (m0 == 0.0 && m1 == 0.0 && m2 == 0.0) {  // a fixed node contributes nothing
          idx += nb;
          continue;
        }
        for (int k = 0; k < nb; ++k) {
          double* c = C + 9 * c_slot_[idx++];
          const int o = 3 * k;
          c[0] += m0 * a0[o], c[1] += m0 * a0[o + 1], c[2] += m0 * a0[o + 2];
          c[3] += m1 * a1[o], c[4] += m1 * a1[o + 1], c[5] += m1 * a1[o + 2];
          c[6] += m2 * a2[o], c[7] += m2 * a2[o + 1], c[8] += m2 * a2[o + 2];
        }
      }
      // Upper blocks of A_c row I = C · P.
      const int up = 3 * diag_k_[I];
      double* r0 = cval + cout[3 * I];
      double* r1 = cval + cout[3 * I + 1];
      double* r2 = cval + cout[3 * I + 2];
      const int len = cout[3 * I + 1] - cout[3 * I];
      std::fill(r0 + up, r0 + len, 0.0);
      std::fill(r1 + up, r1 + len, 0.0);
      std::fill(r2 + up, r2 + len, 0.0);
      int g = g_start_[I];
      const unsigned char* count = g_count_.data() + fine_start_[I];
      for (int s = 0; s < nF; ++s) {
        const double* c = C + 9 * s;
        for (int e = 0; e < count[s]; ++e, ++g) {
          const double w = pval[g_weight_[g]];
          const int o = 3 * g_slot_[g];
          r0[o] += w * c[0], r0[o + 1] += w * c[1], r0[o + 2] += w * c[2];
          r1[o] += w * c[3], r1[o + 1] += w * c[4], r1[o + 2] += w * c[5];
          r2[o] += w * c[6], r2[o + 1] += w * c[7], r2[o + 2] += w * c[8];
        }
      }
    }
    // Lower blocks: A_c(I, J) = A_c(J, I)ᵀ, after every upper block is done (the barrier above).
#pragma omp for schedule(static)
    for (int I = 0; I < nc; ++I)
      for (int m = mirror_start_[I]; m < mirror_start_[I + 1]; ++m) {
        const int o = 3 * mirror_dst_[m], J = mirror_node_[m], oj = 3 * mirror_k_[m];
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c) cval[cout[3 * I + r] + o + c] = cval[cout[3 * J + c] + oj + r];
      }
  }
}

// ---------------------------------------------------------------------------------------------------
// V-cycle

struct MultigridPreconditioner::Level {
  const SparseMatrix* A = nullptr;  // level 0: the caller's matrix; else the Galerkin operator
  SparseMatrix* owned = nullptr;    // coarse levels: writable (unit diagonals of empty rows)
  int nodes = 0;
  std::vector<int> diag_block;  // per node: block index of its diagonal block
  std::vector<double> dinv;     // per node: inverse of its 3×3 diagonal block, row-major
  std::vector<double> free;     // per DOF: 1 free, 0 decoupled (fixed)
  std::vector<int> colour_start, colour_node;
  // The operator in 3×3 blocks of floats for the V-cycle's sweeps (residuals and smoothing): one
  // column index per block instead of nine and 4-byte values move 2.7× fewer bytes than the CSR
  // matrix. Refreshed from A whenever A changes.
  std::vector<int> block_start, block_col;  // per node: its blocks; per block: its column node
  std::vector<float> block_val;             // per block: 9 values, row-major
  // Transfer to the next coarser level: children (Pᵀ) of each coarse node.
  std::vector<int> child_start, child;
  std::vector<double> child_weight;
  Eigen::VectorXd b, x, t;
  Eigen::VectorXd d;           // Chebyshev: the last update direction
  double omega = 0.0;          // Jacobi damping
  double lambda_max = 0.0;     // Chebyshev: upper end of the interval
  Eigen::VectorXd eigenvector;  // last power-iteration vector (warm start)
};

MultigridPreconditioner::MultigridPreconditioner(std::vector<NodeProlongation> prolongations,
                                                 MultigridOptions options)
    : options_(options), prolongations_(std::move(prolongations)) {
  for (auto& P : prolongations_) P.makeCompressed();
  for (size_t l = 0; l + 1 < prolongations_.size(); ++l)
    if (prolongations_[l].cols() != prolongations_[l + 1].rows())
      throw std::invalid_argument("multigrid: prolongation " + std::to_string(l) + " has " +
                                  std::to_string(prolongations_[l].cols()) + " coarse nodes, prolongation " +
                                  std::to_string(l + 1) + " " + std::to_string(prolongations_[l + 1].rows()) +
                                  " fine nodes");
  if (options_.pre_smoothing_steps < 0 || options_.post_smoothing_steps < 0 ||
      !(options_.jacobi_damping >= 0 && options_.jacobi_damping <= 1) || !(options_.coarsest_diagonal_shift >= 0) ||
      !(options_.fine_eigenvalue_bound >= 0) ||
      options_.coarse_update_interval < 1 || options_.power_iterations < 1 || options_.dense_coarsest_max_dofs < 0)
    throw std::invalid_argument(
        "multigrid: smoothing steps must be ≥ 0, the Jacobi damping in [0, 1], the coarsest shift and the "
        "eigenvalue bound ≥ 0, the coarse update interval and the power iterations ≥ 1, the dense coarsest size ≥ 0");
  if (!(options_.coarse_update_cost_iterations > 0.0) || !std::isfinite(options_.coarse_update_cost_iterations))
    throw std::invalid_argument("multigrid: coarse_update_cost_iterations = " +
                                std::to_string(options_.coarse_update_cost_iterations) +
                                " must be a finite number of PCG iterations > 0 (e.g. 5)");
  if (!(options_.chebyshev_ratio > 1.0) || !std::isfinite(options_.chebyshev_ratio) ||
      !(options_.chebyshev_eigenvalue_safety >= 1.0) || !std::isfinite(options_.chebyshev_eigenvalue_safety))
    throw std::invalid_argument("multigrid: chebyshev_ratio = " + std::to_string(options_.chebyshev_ratio) +
                                " must be > 1 (e.g. 10) and chebyshev_eigenvalue_safety = " +
                                std::to_string(options_.chebyshev_eigenvalue_safety) + " ≥ 1 (e.g. 1.1)");
}

MultigridPreconditioner::MultigridPreconditioner(const MeshHierarchy& hierarchy, MultigridOptions options)
    : MultigridPreconditioner(hierarchy.prolongations(), options) {}

MultigridPreconditioner::~MultigridPreconditioner() = default;

const SparseMatrix& MultigridPreconditioner::levelMatrix(int level) const {
  if (level < 0 || level >= numLevels() || !levels_[level]->A)
    throw std::out_of_range("multigrid: no matrix for level " + std::to_string(level) + " (factorize first)");
  return *levels_[level]->A;
}

double MultigridPreconditioner::jacobiDamping(int level) const { return levels_.at(level)->omega; }

double MultigridPreconditioner::chebyshevEigenvalueBound(int level) const {
  return options_.smoother == MultigridOptions::Smoother::kChebyshev ? levels_.at(level)->lambda_max : 0.0;
}

void MultigridPreconditioner::smoothOnly(int level, const Eigen::VectorXd& b, Eigen::VectorXd& x) {
  if (!factorized_) throw std::logic_error("multigrid: smoothOnly() without a successful factorize()");
  if (level < 0 || level + 1 >= numLevels())
    throw std::out_of_range("multigrid: level " + std::to_string(level) + " has no smoother (levels 0 to " +
                            std::to_string(numLevels() - 2) + " have)");
  const Level& lv = *levels_[level];
  if (b.size() != 3 * lv.nodes)
    throw std::invalid_argument("multigrid: smoothOnly() on level " + std::to_string(level) + " with " +
                                std::to_string(b.size()) + " values for " + std::to_string(3 * lv.nodes) + " DOFs");
  x.setZero(b.size());
  const int steps = options_.pre_smoothing_steps;
  if (options_.smoother == MultigridOptions::Smoother::kChebyshev) {
    if (steps > 0) chebyshev(level, b.data(), x.data(), steps, true);
    return;
  }
  for (int s = 0; s < steps; ++s) smooth(level, b.data(), x.data(), true, s == 0);
}

int MultigridPreconditioner::numColours(int level) const {
  return static_cast<int>(levels_.at(level)->colour_start.size()) - 1;
}

void MultigridPreconditioner::analyzePattern(const SparseMatrix& A) {
  const int L = static_cast<int>(prolongations_.size()) + 1;
  const Eigen::Index n0 = prolongations_.empty() ? A.rows() / 3 : prolongations_[0].rows();
  if (A.rows() != 3 * n0 || A.cols() != 3 * n0) {
    std::ostringstream s;
    s << "multigrid: the matrix is " << A.rows() << "×" << A.cols() << ", the hierarchy's fine level has " << n0
      << " nodes (" << 3 * n0 << " DOFs)";
    throw std::invalid_argument(s.str());
  }
  levels_.clear();
  factorized_ = false;
  galerkin_.assign(static_cast<size_t>(L - 1), GalerkinProduct());
  fine_nnz_ = -1;
  for (int l = 0; l < L; ++l) {
    auto lv = std::make_unique<Level>();
    if (l == 0) {
      lv->A = &A;
    } else {
      galerkin_[l - 1].analyze(*levels_[l - 1]->A, prolongations_[l - 1]);
      lv->owned = &galerkin_[l - 1].coarse();
      lv->A = lv->owned;
    }
    const SparseMatrix& M = *lv->A;
    std::vector<int> start, nbr;
    blockGraph(M, "multigrid level " + std::to_string(l), start, nbr, &lv->diag_block);
    const int n = static_cast<int>(M.rows() / 3);
    lv->nodes = n;
    lv->dinv.assign(9 * static_cast<size_t>(n), 0.0);
    lv->free.assign(3 * static_cast<size_t>(n), 1.0);
    lv->b.setZero(3 * n);
    lv->x.setZero(3 * n);
    lv->t.setZero(3 * n);
    if (options_.smoother == MultigridOptions::Smoother::kChebyshev && l + 1 < L) lv->d.setZero(3 * n);
    // Greedy colouring of the node graph: nodes of one colour share no block, so a Gauss–Seidel
    // sweep over one colour is a parallel Jacobi step over independent nodes.
    std::vector<int> colour(static_cast<size_t>(n), -1), seen;
    int colours = 0;
    for (int i = 0; i < n; ++i) {
      seen.assign(static_cast<size_t>(colours) + 1, 0);
      for (int k = start[i]; k < start[i + 1]; ++k)
        if (colour[nbr[k]] >= 0) seen[colour[nbr[k]]] = 1;
      int c = 0;
      while (seen[c]) ++c;
      colour[i] = c;
      colours = std::max(colours, c + 1);
    }
    lv->colour_start.assign(static_cast<size_t>(colours) + 1, 0);
    for (int i = 0; i < n; ++i) ++lv->colour_start[colour[i] + 1];
    for (int c = 0; c < colours; ++c) lv->colour_start[c + 1] += lv->colour_start[c];
    lv->colour_node.resize(static_cast<size_t>(n));
    std::vector<int> fill(lv->colour_start.begin(), lv->colour_start.end() - 1);
    for (int i = 0; i < n; ++i) lv->colour_node[fill[colour[i]]++] = i;
    lv->block_start = std::move(start);
    lv->block_col = std::move(nbr);
    if (l + 1 < L) {  // a smoothed level (the coarsest is solved directly as it is)
      lv->block_val.assign(9 * lv->block_col.size(), 0.0f);
      const NodeProlongation& P = prolongations_[l];
      const int nc = static_cast<int>(P.cols());
      lv->child_start.assign(static_cast<size_t>(nc) + 1, 0);
      for (int k = 0; k < P.nonZeros(); ++k) ++lv->child_start[P.innerIndexPtr()[k] + 1];
      for (int I = 0; I < nc; ++I) lv->child_start[I + 1] += lv->child_start[I];
      lv->child.resize(static_cast<size_t>(P.nonZeros()));
      lv->child_weight.resize(lv->child.size());
      std::vector<int> f(lv->child_start.begin(), lv->child_start.end() - 1);
      for (int i = 0; i < P.rows(); ++i)
        for (int k = P.outerIndexPtr()[i]; k < P.outerIndexPtr()[i + 1]; ++k) {
          const int I = P.innerIndexPtr()[k];
          lv->child[f[I]] = i;
          lv->child_weight[f[I]++] = P.valuePtr()[k];
        }
    }
    levels_.push_back(std::move(lv));
  }
  const Eigen::Index coarsest_dofs = levels_.back()->A->rows();
  dense_coarsest_ = L > 1 && coarsest_dofs <= options_.dense_coarsest_max_dofs;
  if (dense_coarsest_) {
    coarsest_dense_.setZero(coarsest_dofs, coarsest_dofs);
    coarsest_llt_ = Eigen::LLT<Eigen::MatrixXd>(coarsest_dofs);
  } else {
    coarsest_dense_.resize(0, 0);
    coarsest_.analyzePattern(*levels_.back()->A);
  }
  fine_nnz_ = A.nonZeros();
  fine_outer_.assign(A.outerIndexPtr(), A.outerIndexPtr() + A.rows() + 1);
  fine_only_ = 0;
  renew_requested_ = true;  // the first factorize() makes the coarse operators
  rate_count_ = 0;
  lost_iterations_ = 0.0;
  factorized_ = false;
}

void MultigridPreconditioner::scanLevel(int l) {
  Level& lv = *levels_[l];
  const SparseMatrix& M = *lv.A;
  const int* outer = M.outerIndexPtr();
  double* val = lv.owned ? lv.owned->valuePtr() : nullptr;
  const double* cval = M.valuePtr();
  // The coarsest level is solved directly: it only needs its empty rows fixed.
  const bool smoother = l + 1 < numLevels() || numLevels() == 1;
  int bad = -1;
#pragma omp parallel for schedule(static) if (lv.nodes > kParallelMinNodes)
  for (int i = 0; i < lv.nodes; ++i) {
    double d[9];
    for (int r = 0; r < 3; ++r) {
      const int row = 3 * i + r;
      const int d0 = outer[row] + 3 * lv.diag_block[i];
      bool coupled = false;
      for (int k = outer[row]; k < outer[row + 1] && !coupled; ++k) coupled = (k != d0 + r && cval[k] != 0.0);
      // A coarse DOF that only interpolates fixed fine DOFs has an empty row: make it decoupled.
      if (!coupled && val && cval[d0 + r] == 0.0) val[d0 + r] = 1.0;
      lv.free[row] = coupled ? 1.0 : 0.0;
      for (int c = 0; c < 3; ++c) d[3 * r + c] = cval[d0 + c];
    }
    if (!smoother) continue;
    // Inverse by cofactors; Sylvester's criterion for positive definiteness.
    const double c00 = d[4] * d[8] - d[5] * d[7], c01 = d[2] * d[7] - d[1] * d[8], c02 = d[1] * d[5] - d[2] * d[4];
    const double c10 = d[5] * d[6] - d[3] * d[8], c11 = d[0] * d[8] - d[2] * d[6], c12 = d[2] * d[3] - d[0] * d[5];
    const double c20 = d[3] * d[7] - d[4] * d[6], c21 = d[1] * d[6] - d[0] * d[7], c22 = d[0] * d[4] - d[1] * d[3];
    const double det = d[0] * c00 + d[1] * c10 + d[2] * c20;
    if (!(d[0] > 0.0 && c22 > 0.0 && det > 0.0) || !std::isfinite(det)) {
#pragma omp critical(multigrid_bad_block)
      if (bad < 0 || i < bad) bad = i;
      continue;
    }
    const double inv = 1.0 / det;
    double* out = lv.dinv.data() + 9 * static_cast<size_t>(i);
    out[0] = c00 * inv, out[1] = c01 * inv, out[2] = c02 * inv;
    out[3] = c10 * inv, out[4] = c11 * inv, out[5] = c12 * inv;
    out[6] = c20 * inv, out[7] = c21 * inv, out[8] = c22 * inv;
  }
  if (bad >= 0) {
    std::ostringstream s;
    s << "multigrid: the matrix is not positive definite: the 3×3 diagonal block of node " << bad;
    if (l > 0) s << " of coarse level " << l;
    s << " is not positive definite (diagonal";
    for (int r = 0; r < 3; ++r) s << " " << cval[outer[3 * bad + r] + 3 * lv.diag_block[bad] + r];
    s << ")";
    throw std::runtime_error(s.str());
  }
}

void MultigridPreconditioner::estimateDamping(int l) {
  Level& lv = *levels_[l];
  const bool chebyshev = options_.smoother == MultigridOptions::Smoother::kChebyshev;
  if (!chebyshev && options_.jacobi_damping > 0.0) {
    lv.omega = options_.jacobi_damping;
    return;
  }
  if (l == 0 && options_.fine_eigenvalue_bound > 0.0) {
    lv.omega = std::min(1.0, 1.8 / options_.fine_eigenvalue_bound);
    lv.lambda_max = options_.fine_eigenvalue_bound;  // a bound: no safety factor
    return;
  }
  if (lv.block_val.empty()) return;  // a level solved directly (a hierarchy of one): no smoother
  // Power iteration on D⁻¹A: its largest eigenvalue bounds the damping (ω λ_max < 2).
  const int n = 3 * lv.nodes;
  int iterations = options_.power_iterations;
  if (lv.eigenvector.size() != n) {
    lv.eigenvector.resize(n);
    uint64_t state = 0x9e3779b97f4a7c15ULL;  // a fixed pseudo-random start: reproducible
    for (int i = 0; i < n; ++i) {
      state = state * 6364136223846793005ULL + 1442695040888963407ULL;
      lv.eigenvector[i] = static_cast<double>(state >> 11) / 9007199254740992.0 - 0.5;
    }
    // A cold start needs many more iterations: 3 × 4 = 12 once underestimated λ_max by a third on a
    // Galerkin level (ω λ_max = 2.05, a divergent smoother); 3 × 12 = 36 do not, measured over repeated runs.
    iterations *= 12;
  }
  double* v = lv.eigenvector.data();
  double* Av = lv.t.data();
  const double* dinv = lv.dinv.data();
  const double* fr = lv.free.data();
  // A v from the float blocks the smoother sweeps (toBlocks() ran first): the operator the damping
  // is for, at 2.7× fewer bytes than the CSR matrix. The products come out negated (0 − A v), which
  // the iteration does not see (y flips sign each time; λ is a ratio of norms).
  const float* bval = lv.block_val.data();
  const int* bcol = lv.block_col.data();
  const int* bstart = lv.block_start.data();
  static constexpr double kZero[3] = {0.0, 0.0, 0.0};
  double lambda = 0.0;
  for (int it = 0; it < iterations; ++it) {
    double vv = 0.0, yy = 0.0;
#pragma omp parallel if (lv.nodes > kParallelMinNodes)
    {
#pragma omp for schedule(static)
      for (int i = 0; i < lv.nodes; ++i) blockRowResidual(bval, bcol, bstart[i], bstart[i + 1], kZero, v, Av + 3 * i);
#pragma omp for schedule(static) reduction(+ : vv, yy)
      for (int i = 0; i < lv.nodes; ++i) {
        const double* d = dinv + 9 * i;
        const double* a = Av + 3 * i;
        double* y = v + 3 * i;
        vv += y[0] * y[0] + y[1] * y[1] + y[2] * y[2];
        // Fixed DOFs (eigenvalue 1 of D⁻¹A) are left out of the iteration.
        const double y0 = fr[3 * i] * (d[0] * a[0] + d[1] * a[1] + d[2] * a[2]);
        const double y1 = fr[3 * i + 1] * (d[3] * a[0] + d[4] * a[1] + d[5] * a[2]);
        const double y2 = fr[3 * i + 2] * (d[6] * a[0] + d[7] * a[1] + d[8] * a[2]);
        y[0] = y0, y[1] = y1, y[2] = y2;
        yy += y0 * y0 + y1 * y1 + y2 * y2;
      }
    }
    if (!(yy > 0.0) || !(vv > 0.0)) break;
    lambda = std::sqrt(yy / vv);
    lv.eigenvector *= 1.0 / std::sqrt(yy);
  }
  // Power iteration approaches λ_max from below; ω = 1.2 / λ keeps ω λ_max < 1.9 as long as the
  // estimate is within 37 % of λ_max.
  lv.omega = lambda > 0.0 ? std::min(1.0, 1.2 / lambda) : 0.5;
  // Chebyshev: the polynomial stays below 1 in magnitude up to λ_max (1 + 1/ratio), so with the
  // safety factor 1.1 and ratio 10 an estimate within 21 % of the true λ_max suffices.
  lv.lambda_max = options_.chebyshev_eigenvalue_safety * (lambda > 0.0 ? lambda : 4.0);
}

void MultigridPreconditioner::factorize(const SparseMatrix& A) {
  if (fine_nnz_ < 0) throw std::logic_error("multigrid: factorize() called before analyzePattern()");
  // Same size, entry count and row lengths: the float blocks and the Galerkin index lists are laid
  // out over the analysed rows.
  if (A.rows() != levels_[0]->A->rows() || A.nonZeros() != fine_nnz_ ||
      !std::equal(fine_outer_.begin(), fine_outer_.end(), A.outerIndexPtr()))
    throw std::logic_error("multigrid: the matrix pattern changed since analyzePattern()");
  factorized_ = false;
  timings_.scan_s = timings_.damping_s = timings_.galerkin_s = timings_.coarse_factorize_s = 0.0;
  timings_.applications = 0;
  timings_.level_s.resize(levels_.size());  // allocates once
  std::fill(timings_.level_s.begin(), timings_.level_s.end(), 0.0);
  levels_[0]->A = &A;
  // Coarse renewal: at the first factorization (and after one that failed), after
  // coarse_update_interval − 1 fine-only ones, or early when the adaptive rule asked for it
  // (reportConvergence).
  const bool coarse = numLevels() == 1 || renew_requested_ || fine_only_ + 1 >= options_.coarse_update_interval;
  const int L = coarse ? numLevels() : 1;
  for (int l = 0; l < L; ++l) {
    auto t0 = Clock::now();
    if (l > 0) {
      galerkin_[l - 1].compute(*levels_[l - 1]->A, levels_[l - 1]->free.data());
      timings_.galerkin_s += since(t0);
      t0 = Clock::now();
    }
    // The coarsest level needs no smoother, only the unit diagonals of empty rows.
    scanLevel(l);
    if (l + 1 < numLevels()) toBlocks(l);
    timings_.scan_s += since(t0);
    if (coarse && options_.smoother != MultigridOptions::Smoother::kGaussSeidel && (l + 1 < numLevels() || l == 0)) {
      t0 = Clock::now();
      estimateDamping(l);
      timings_.damping_s += since(t0);
    }
  }
  if (!coarse) {
    ++fine_only_;
    factorized_ = true;
    return;
  }
  const auto t0 = Clock::now();
  Level& last = *levels_.back();
  if (last.owned && options_.coarsest_diagonal_shift > 0.0) {
    const int* outer = last.owned->outerIndexPtr();
    double* val = last.owned->valuePtr();
    for (int i = 0; i < last.nodes; ++i)
      for (int r = 0; r < 3; ++r) val[outer[3 * i + r] + 3 * last.diag_block[i] + r] *= 1.0 + options_.coarsest_diagonal_shift;
  }
  if (dense_coarsest_) {
    const SparseMatrix& C = *last.A;
    coarsest_dense_.setZero();
    for (Eigen::Index r = 0; r < C.rows(); ++r)
      for (int k = C.outerIndexPtr()[r]; k < C.outerIndexPtr()[r + 1]; ++k)
        coarsest_dense_(r, C.innerIndexPtr()[k]) = C.valuePtr()[k];
    coarsest_llt_.compute(coarsest_dense_);
    if (coarsest_llt_.info() != Eigen::Success)
      throw std::runtime_error("multigrid: coarsest level " + std::to_string(L - 1) + ": the " +
                               std::to_string(C.rows()) +
                               "-DOF Galerkin operator is not positive definite (dense Cholesky failed); check the "
                               "stiffness (inverted elements, negative moduli)");
  } else {
    try {
      coarsest_.factorize(*last.A);
    } catch (const std::runtime_error& e) {
      throw std::runtime_error("multigrid: coarsest level " + std::to_string(L - 1) + ": " + e.what());
    }
  }
  timings_.coarse_factorize_s = since(t0);
  ++coarse_renewals_;
  fine_only_ = 0;
  renew_requested_ = false;
  rate_count_ = 0;
  lost_iterations_ = 0.0;
  factorized_ = true;
}

void MultigridPreconditioner::reportConvergence(int iterations, double residual_reduction) {
  if (!options_.coarse_update_adaptive || iterations < 1 || numLevels() == 1) return;
  if (!std::isfinite(residual_reduction)) {  // a broken solve: start afresh
    renew_requested_ = true;
    return;
  }
  if (residual_reduction == 0.0) return;  // solved exactly: nothing to measure
  const double cost = options_.coarse_update_cost_iterations;
  if (residual_reduction >= 1.0) {
    // CG's residual norm need not fall in every iteration: a capped solve of a few iterations can
    // end above its start with sound coarse operators. Its iterations count as lost.
    if (rate_count_ > 0) lost_iterations_ += iterations;
  } else {
    const double log_rate = std::log(residual_reduction) / iterations;  // < 0: log of the mean reduction per iteration
    if (rate_count_++ == 0) {
      first_log_rate_ = log_rate;  // the reference: fresh coarse operators
      lost_iterations_ = 0.0;
      return;
    }
    // At the reference rate the same reduction takes iterations · ρ/ρ_0 iterations: the rest was
    // lost. Faster solves give iterations back, at most one renewal's worth in all: a reference
    // taken at an unusually slow solve cannot bank credit that holds the renewal off for good.
    lost_iterations_ = std::max(-cost, lost_iterations_ + iterations * (1.0 - log_rate / first_log_rate_));
  }
  if (lost_iterations_ >= cost) renew_requested_ = true;
}

void MultigridPreconditioner::toBlocks(int l) {
  Level& lv = *levels_[l];
  const SparseMatrix& M = *lv.A;
  const int* outer = M.outerIndexPtr();
  const double* val = M.valuePtr();
  float* out = lv.block_val.data();
#pragma omp parallel for schedule(static) if (lv.nodes > kParallelMinNodes)
  for (int i = 0; i < lv.nodes; ++i) {
    const int b0 = lv.block_start[i], nb = lv.block_start[i + 1] - b0;
    for (int r = 0; r < 3; ++r) {
      const double* v = val + outer[3 * i + r];
      float* o = out + 9 * static_cast<size_t>(b0) + 3 * r;
      for (int k = 0; k < nb; ++k)
        for (int c = 0; c < 3; ++c) o[9 * k + c] = static_cast<float>(v[3 * k + c]);
    }
  }
}

void MultigridPreconditioner::residual(int l, const double* b, const double* x, double* t) {
  const Level& lv = *levels_[l];
  const float* val = lv.block_val.data();
  const int* col = lv.block_col.data();
  const int* start = lv.block_start.data();
  blockResidual(val, col, start, b, x, t, lv.nodes, options_.simd_kernels, lv.nodes > kParallelMinNodes);
}

void MultigridPreconditioner::smooth(int l, const double* b, double* x, bool forward, bool from_zero) {
  Level& lv = *levels_[l];
  const double* dinv = lv.dinv.data();
  const int n = lv.nodes;
  if (options_.smoother == MultigridOptions::Smoother::kJacobi) {
    const double w = lv.omega;
    const double* t = b;
    if (!from_zero) {
      residual(l, b, x, lv.t.data());
      t = lv.t.data();
    }
#pragma omp parallel for schedule(static) if (n > kParallelMinNodes)
    for (int i = 0; i < n; ++i) {
      const double* d = dinv + 9 * i;
      const double* s = t + 3 * i;
      double* xi = x + 3 * i;
      const double d0 = w * (d[0] * s[0] + d[1] * s[1] + d[2] * s[2]);
      const double d1 = w * (d[3] * s[0] + d[4] * s[1] + d[5] * s[2]);
      const double d2 = w * (d[6] * s[0] + d[7] * s[1] + d[8] * s[2]);
      if (from_zero) xi[0] = d0, xi[1] = d1, xi[2] = d2;
      else xi[0] += d0, xi[1] += d1, xi[2] += d2;
    }
    return;
  }
  if (from_zero) std::fill(x, x + 3 * n, 0.0);
  const float* val = lv.block_val.data();
  const int* col = lv.block_col.data();
  const int* start = lv.block_start.data();
  auto relax = [&](int i) {
    double r[3];
    blockRowResidual(val, col, start[i], start[i + 1], b + 3 * i, x, r);
    const double* d = dinv + 9 * i;
    x[3 * i] += d[0] * r[0] + d[1] * r[1] + d[2] * r[2];
    x[3 * i + 1] += d[3] * r[0] + d[4] * r[1] + d[5] * r[2];
    x[3 * i + 2] += d[6] * r[0] + d[7] * r[1] + d[8] * r[2];
  };
  const int colours = static_cast<int>(lv.colour_start.size()) - 1;
#pragma omp parallel if (n > kParallelMinNodes)
  for (int cc = 0; cc < colours; ++cc) {
    const int c = forward ? cc : colours - 1 - cc;
#pragma omp for schedule(static)
    for (int p = lv.colour_start[c]; p < lv.colour_start[c + 1]; ++p) relax(lv.colour_node[p]);
  }
}

// Chebyshev iteration for A x = b preconditioned by D [AB03; Saad, Iterative Methods, Alg. 12.1]:
// with θ = (λ_max + λ_min)/2, δ = (λ_max − λ_min)/2, σ = θ/δ and ρ₀ = 1/σ,
//   d₀ = D⁻¹ r₀ / θ,   d_k = ρ_k ρ_{k−1} d_{k−1} + (2 ρ_k / δ) D⁻¹ r_k,   ρ_k = 1/(2σ − ρ_{k−1}),
//   x_{k+1} = x_k + d_k,   r_k = b − A x_k,
// so the error after `degree` updates is T_k((θ − D⁻¹A)/δ) / T_k(σ) times the initial one.
void MultigridPreconditioner::chebyshev(int l, const double* b, double* x, int degree, bool from_zero) {
  Level& lv = *levels_[l];
  const double* dinv = lv.dinv.data();
  const int n = lv.nodes;
  const double upper = lv.lambda_max, lower = upper / options_.chebyshev_ratio;
  const double theta = 0.5 * (upper + lower), delta = 0.5 * (upper - lower), sigma = theta / delta;
  const float* val = lv.block_val.data();
  const int* col = lv.block_col.data();
  const int* start = lv.block_start.data();
  double* d = lv.d.data();
  double rho = 1.0 / sigma;
  // Step k: d = alpha d + beta D⁻¹ (b − A x), then x += d (a second pass: the residuals read x).
  for (int k = 0; k < degree; ++k) {
    const double rho_new = k == 0 ? rho : 1.0 / (2.0 * sigma - rho);
    const double alpha = k == 0 ? 0.0 : rho_new * rho, beta = k == 0 ? 1.0 / theta : 2.0 * rho_new / delta;
    const bool zero = from_zero && k == 0;
#pragma omp parallel if (n > kParallelMinNodes)
    {
#pragma omp for schedule(static)
      for (int i = 0; i < n; ++i) {
        double r[3];
        if (zero) r[0] = b[3 * i], r[1] = b[3 * i + 1], r[2] = b[3 * i + 2];
        else blockRowResidual(val, col, start[i], start[i + 1], b + 3 * i, x, r);
        const double* m = dinv + 9 * i;
        double* di = d + 3 * i;
        const double z0 = m[0] * r[0] + m[1] * r[1] + m[2] * r[2];
        const double z1 = m[3] * r[0] + m[4] * r[1] + m[5] * r[2];
        const double z2 = m[6] * r[0] + m[7] * r[1] + m[8] * r[2];
        if (k == 0) di[0] = beta * z0, di[1] = beta * z1, di[2] = beta * z2;
        else di[0] = alpha * di[0] + beta * z0, di[1] = alpha * di[1] + beta * z1, di[2] = alpha * di[2] + beta * z2;
      }
#pragma omp for schedule(static)
      for (int j = 0; j < 3 * n; ++j) x[j] = zero ? d[j] : x[j] + d[j];
    }
    rho = rho_new;
  }
}

void MultigridPreconditioner::vcycle(int l, const double* b, double* x) {
  auto t0 = Clock::now();
  Level& lv = *levels_[l];
  Level& next = *levels_[l + 1];
  const int pre = options_.pre_smoothing_steps, post = options_.post_smoothing_steps;
  const bool chebyshev_smoother = options_.smoother == MultigridOptions::Smoother::kChebyshev;
  if (pre == 0) std::fill(x, x + 3 * lv.nodes, 0.0);
  if (chebyshev_smoother && pre > 0) chebyshev(l, b, x, pre, true);
  else
    for (int s = 0; s < pre; ++s) smooth(l, b, x, true, s == 0);
  residual(l, b, x, lv.t.data());

  // Restriction b_c = (D P)ᵀ t.
  const double* t = lv.t.data();
  const double* fr = lv.free.data();
  double* bc = next.b.data();
  const int nc = next.nodes;
#pragma omp parallel for schedule(static) if (nc > kParallelMinNodes / 4)
  for (int I = 0; I < nc; ++I) {
    double s0 = 0.0, s1 = 0.0, s2 = 0.0;
    for (int k = lv.child_start[I]; k < lv.child_start[I + 1]; ++k) {
      const int i = 3 * lv.child[k];
      const double w = lv.child_weight[k];
      s0 += w * fr[i] * t[i];
      s1 += w * fr[i + 1] * t[i + 1];
      s2 += w * fr[i + 2] * t[i + 2];
    }
    bc[3 * I] = s0, bc[3 * I + 1] = s1, bc[3 * I + 2] = s2;
  }

  timings_.level_s[l] += since(t0);
  if (l + 2 == numLevels()) {
    t0 = Clock::now();
    if (dense_coarsest_) next.x = coarsest_llt_.solve(next.b);  // into next.x's storage, no allocation
    else coarsest_.solve(next.b, next.x);
    timings_.level_s[l + 1] += since(t0);
  } else {
    vcycle(l + 1, next.b.data(), next.x.data());
  }
  t0 = Clock::now();

  // Prolongation x += (D P) x_c.
  const NodeProlongation& P = prolongations_[l];
  const int* pout = P.outerIndexPtr();
  const int* pin = P.innerIndexPtr();
  const double* pval = P.valuePtr();
  const double* xc = next.x.data();
#pragma omp parallel for schedule(static) if (lv.nodes > kParallelMinNodes)
  for (int i = 0; i < lv.nodes; ++i) {
    double s0 = 0.0, s1 = 0.0, s2 = 0.0;
    for (int k = pout[i]; k < pout[i + 1]; ++k) {
      const int J = 3 * pin[k];
      s0 += pval[k] * xc[J];
      s1 += pval[k] * xc[J + 1];
      s2 += pval[k] * xc[J + 2];
    }
    x[3 * i] += fr[3 * i] * s0;
    x[3 * i + 1] += fr[3 * i + 1] * s1;
    x[3 * i + 2] += fr[3 * i + 2] * s2;
  }
  if (chebyshev_smoother && post > 0) chebyshev(l, b, x, post, false);
  else
    for (int s = 0; s < post; ++s) smooth(l, b, x, false, false);
  timings_.level_s[l] += since(t0);
}

void MultigridPreconditioner::apply(const Eigen::VectorXd& r, Eigen::VectorXd& z) {
  if (!factorized_) throw std::logic_error("multigrid: apply() without a successful factorize()");
  ++timings_.applications;
  if (numLevels() == 1) {
    const auto t0 = Clock::now();
    coarsest_.solve(r, z);
    timings_.level_s[0] += since(t0);
    return;
  }
  vcycle(0, r.data(), z.data());
}

MultigridPcgSolver::MultigridPcgSolver(const MeshHierarchy& hierarchy, PcgOptions pcg_options,
                                       MultigridOptions multigrid_options)
    : PcgSolver(pcg_options, std::make_unique<MultigridPreconditioner>(hierarchy, multigrid_options)) {}

MultigridPcgSolver::MultigridPcgSolver(std::vector<NodeProlongation> prolongations, PcgOptions pcg_options,
                                       MultigridOptions multigrid_options)
    : PcgSolver(pcg_options,
                std::make_unique<MultigridPreconditioner>(std::move(prolongations), multigrid_options)) {}

}  // namespace breast_sim::core
