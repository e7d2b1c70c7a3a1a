// The mesh hierarchy of the geometric multigrid: barycentric prolongation between non-nested
// meshes of one domain, and the coarse meshes of a case's tissue.
#include "breast_sim/core/solver/multigrid.h"

#include <sstream>
#include <stdexcept>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/point_embedding.h"

namespace breast_sim::core {

namespace {

double meanBoundaryEdge(const TetMesh& mesh) {
  const Triangles& f = mesh.boundary().triangles;
  if (f.rows() == 0) return 0.0;
  const Points& x = mesh.nodes();
  double sum = 0.0;
  for (Eigen::Index t = 0; t < f.rows(); ++t)
    for (int e = 0; e < 3; ++e) sum += (x.row(f(t, e)) - x.row(f(t, (e + 1) % 3))).norm();
  return sum / (3.0 * static_cast<double>(f.rows()));
}

}  // namespace

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
    throw std::invalid_argument("the geometric multigrid needs coarse meshes of the model, meshed from its label "
                                "image: this model was not meshed from an image (no meshing report). Build it "
                                "with buildSimulationModel(), or choose the solver 'aggregation' (smoothed "
                                "aggregation, no coarse meshes) or 'cholmod' (direct)");
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

}  // namespace breast_sim::core
