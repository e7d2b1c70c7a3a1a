#pragma once
/// @file elastic_material.h
/// Linear isotropic elastic material of the co-rotated model.

namespace breast_sim::core {

/// Isotropic linear elasticity with a density. Defaults are the seed paper's breast values
/// (E = 2 kPa, ν = 0.48 [HHM*11]) and the density of water.
struct ElasticMaterial {
  double youngs_modulus_pa = 2000.0;  ///< E0 [Pa]; the per-element modulus factor E_r scales it
  double poisson_ratio = 0.48;        ///< ν, in (−1, 0.5); linear tetrahedra lock as ν → 0.5
  double density_kg_per_m3 = 1000.0;  ///< ρ [kg/m³]

  /// Lamé's first parameter λ = Eν / ((1+ν)(1−2ν)) [Pa].
  double lameLambda() const {
    return youngs_modulus_pa * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio));
  }
  /// Shear modulus μ = E / (2(1+ν)) [Pa].
  double lameMu() const { return youngs_modulus_pa / (2.0 * (1.0 + poisson_ratio)); }

  /// @throws std::invalid_argument naming the field, its value and the accepted range.
  void validate() const;
};

}  // namespace breast_sim::core
