#include "breast_sim/core/fem/corotated_tet_fem.h"

#include <cmath>
#include <stdexcept>

#include <Eigen/Dense>

#include "breast_sim/core/fem/polar_decomposition.h"

namespace breast_sim::core {

CorotatedTetFem::CorotatedTetFem(const TetMesh& mesh, const ElasticMaterial& material)
    : tets_(mesh.tets()), rest_(mesh.nodes()), material_(material), pattern_(mesh.tets(), mesh.numNodes()) {
  material_.validate();
  lambda_ = material_.lameLambda();
  mu_ = material_.lameMu();
  const int nt = mesh.numTets();
  grads_.resize(12 * static_cast<size_t>(nt));
  volumes_.resize(nt);
  rotations_.assign(9 * static_cast<size_t>(nt), 0.0);
  rotated_grads_.assign(12 * static_cast<size_t>(nt), 0.0);
  elem_forces_.assign(12 * static_cast<size_t>(nt), 0.0);
  modulus_factor_ = Eigen::VectorXd::Ones(nt);
  von_mises_ = Eigen::VectorXd::Zero(nt);
#pragma omp parallel for schedule(static)
  for (int e = 0; e < nt; ++e) {
    const Eigen::Vector3d a = rest_.row(tets_(e, 0));
    Eigen::Matrix3d Dm;
    for (int k = 0; k < 3; ++k) Dm.col(k) = Eigen::Vector3d(rest_.row(tets_(e, k + 1))) - a;
    volumes_[e] = Dm.determinant() / 6.0;
    // Rows of Dm⁻¹ are ∇N_1..∇N_3; ∇N_0 = −their sum.
    const Eigen::Matrix3d Dinv = Dm.inverse();
    double* g = &grads_[12 * static_cast<size_t>(e)];
    for (int i = 1; i < 4; ++i)
      for (int c = 0; c < 3; ++c) g[3 * i + c] = Dinv(i - 1, c);
    for (int c = 0; c < 3; ++c) g[c] = -(g[3 + c] + g[6 + c] + g[9 + c]);
    Eigen::Map<Eigen::Matrix3d>(&rotations_[9 * static_cast<size_t>(e)]).setIdentity();
    std::copy(g, g + 12, &rotated_grads_[12 * static_cast<size_t>(e)]);
  }
}

void CorotatedTetFem::setModulusFactors(const Eigen::VectorXd& factors) {
  if (factors.size() != modulus_factor_.size())
    throw std::invalid_argument("setModulusFactors: " + std::to_string(factors.size()) + " factors for " +
                                std::to_string(modulus_factor_.size()) + " elements");
  for (Eigen::Index e = 0; e < factors.size(); ++e)
    if (!(factors[e] > 0) || !std::isfinite(factors[e]))
      throw std::invalid_argument("setModulusFactors: factor of element " + std::to_string(e) + " is " +
                                  std::to_string(factors[e]) + "; factors must be positive and finite");
  modulus_factor_ = factors;
}

void CorotatedTetFem::update(const Points& x, Eigen::VectorXd& f) {
  const int nt = static_cast<int>(tets_.rows());
  // Per element: rotation, co-rotated strain and stress, element forces −V R σ ∇N_i.
#pragma omp parallel for schedule(static)
  for (int e = 0; e < nt; ++e) {
    const double* g = &grads_[12 * static_cast<size_t>(e)];
    Eigen::Matrix3d F = Eigen::Matrix3d::Zero();  // Σ_i x_i ∇N_iᵀ
    for (int i = 0; i < 4; ++i) {
      const Eigen::Vector3d xi = x.row(tets_(e, i));
      F.noalias() += xi * Eigen::RowVector3d(g[3 * i], g[3 * i + 1], g[3 * i + 2]);
    }
    Eigen::Map<Eigen::Matrix3d> R(&rotations_[9 * static_cast<size_t>(e)]);
    if (corotated_) R = rotationOf(F);
    const Eigen::Matrix3d Fr = R.transpose() * F;
    const Eigen::Matrix3d eps = 0.5 * (Fr + Fr.transpose()) - Eigen::Matrix3d::Identity();
    const double s = modulus_factor_[e];
    const Eigen::Matrix3d sigma = s * (lambda_ * eps.trace() * Eigen::Matrix3d::Identity() + 2.0 * mu_ * eps);
    const double d01 = sigma(0, 0) - sigma(1, 1), d12 = sigma(1, 1) - sigma(2, 2), d20 = sigma(2, 2) - sigma(0, 0);
    von_mises_[e] = std::sqrt(0.5 * (d01 * d01 + d12 * d12 + d20 * d20) +
                              3.0 * (sigma(0, 1) * sigma(0, 1) + sigma(1, 2) * sigma(1, 2) + sigma(0, 2) * sigma(0, 2)));
    const Eigen::Matrix3d RS = -volumes_[e] * (R * sigma);
    double* fe = &elem_forces_[12 * static_cast<size_t>(e)];
    double* rg = &rotated_grads_[12 * static_cast<size_t>(e)];
    for (int i = 0; i < 4; ++i) {
      const Eigen::Vector3d gi(g[3 * i], g[3 * i + 1], g[3 * i + 2]);
      const Eigen::Vector3d fi = RS * gi;
      fe[3 * i] = fi.x();
      fe[3 * i + 1] = fi.y();
      fe[3 * i + 2] = fi.z();
      // R ∇N_i, kept for the stiffness assembly (each element's blocks are gathered by 4 nodes).
      Eigen::Map<Eigen::Vector3d>(rg + 3 * i) = R * gi;
    }
  }
  // Gather per node.
  const int nn = pattern_.numNodes();
  f.setZero(3 * nn);
#pragma omp parallel for schedule(static)
  for (int n = 0; n < nn; ++n) {
    double fx = 0, fy = 0, fz = 0;
    for (int k = pattern_.incidentStart(n); k < pattern_.incidentStart(n + 1); ++k) {
      const double* fe = &elem_forces_[12 * static_cast<size_t>(pattern_.incidentElement(k)) + 3 * pattern_.incidentLocal(k)];
      fx += fe[0];
      fy += fe[1];
      fz += fe[2];
    }
    f[3 * n] = fx;
    f[3 * n + 1] = fy;
    f[3 * n + 2] = fz;
  }
}

void CorotatedTetFem::addStiffness(double scale, SparseMatrix& A) const {
  const int nn = pattern_.numNodes();
  double* values = A.valuePtr();
  const int* outer = A.outerIndexPtr();
#pragma omp parallel for schedule(dynamic, 64)
  for (int n = 0; n < nn; ++n) {
    for (int k = pattern_.incidentStart(n); k < pattern_.incidentStart(n + 1); ++k) {
      const int e = pattern_.incidentElement(k), i = pattern_.incidentLocal(k);
      const double* rg = &rotated_grads_[12 * static_cast<size_t>(e)];
      const double w = scale * modulus_factor_[e] * volumes_[e];
      const Eigen::Map<const Eigen::Vector3d> gi(rg + 3 * i);
      const int* slot = pattern_.blockSlot(e) + 4 * i;
      for (int j = 0; j < 4; ++j) {
        const Eigen::Map<const Eigen::Vector3d> gj(rg + 3 * j);
        // Block (i, j) of R K_e0 Rᵀ: V(λ gi gjᵀ + μ gj giᵀ + μ (gi·gj) I).
        const double dot = mu_ * gi.dot(gj);
        for (int r = 0; r < 3; ++r) {
          double* row = values + outer[3 * n + r] + 3 * slot[j];
          const double a = w * lambda_ * gi[r], b = w * mu_ * gj[r];
          row[0] += a * gj[0] + b * gi[0];
          row[1] += a * gj[1] + b * gi[1];
          row[2] += a * gj[2] + b * gi[2];
          row[r] += w * dot;
        }
      }
    }
  }
}

Eigen::MatrixXd CorotatedTetFem::denseStiffness() const {
  const int nn = pattern_.numNodes();
  Eigen::MatrixXd K = Eigen::MatrixXd::Zero(3 * nn, 3 * nn);
  for (int e = 0; e < static_cast<int>(tets_.rows()); ++e) {
    // B (6×12, Voigt order xx yy zz xy yz xz with engineering shear) and C (6×6): K_e0 = V Bᵀ C B.
    const double* g = &grads_[12 * static_cast<size_t>(e)];
    Eigen::Matrix<double, 6, 12> B = Eigen::Matrix<double, 6, 12>::Zero();
    for (int i = 0; i < 4; ++i) {
      const double gx = g[3 * i], gy = g[3 * i + 1], gz = g[3 * i + 2];
      B(0, 3 * i) = gx;
      B(1, 3 * i + 1) = gy;
      B(2, 3 * i + 2) = gz;
      B(3, 3 * i) = gy, B(3, 3 * i + 1) = gx;
      B(4, 3 * i + 1) = gz, B(4, 3 * i + 2) = gy;
      B(5, 3 * i) = gz, B(5, 3 * i + 2) = gx;
    }
    Eigen::Matrix<double, 6, 6> C = Eigen::Matrix<double, 6, 6>::Zero();
    C.topLeftCorner<3, 3>().setConstant(lambda_);
    C.topLeftCorner<3, 3>().diagonal().array() += 2.0 * mu_;
    C.bottomRightCorner<3, 3>().diagonal().setConstant(mu_);
    const Eigen::Matrix<double, 12, 12> K0 = volumes_[e] * B.transpose() * C * B;
    const Eigen::Map<const Eigen::Matrix3d> R(&rotations_[9 * static_cast<size_t>(e)]);
    Eigen::Matrix<double, 12, 12> Rb = Eigen::Matrix<double, 12, 12>::Zero();
    for (int i = 0; i < 4; ++i) Rb.block<3, 3>(3 * i, 3 * i) = R;
    const Eigen::Matrix<double, 12, 12> Ke = modulus_factor_[e] * Rb * K0 * Rb.transpose();
    for (int i = 0; i < 4; ++i)
      for (int j = 0; j < 4; ++j) K.block<3, 3>(3 * tets_(e, i), 3 * tets_(e, j)) += Ke.block<3, 3>(3 * i, 3 * j);
  }
  return K;
}

}  // namespace breast_sim::core
