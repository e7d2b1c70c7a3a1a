#include "breast_sim/core/fem/elastic_material.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

namespace breast_sim::core {

void ElasticMaterial::validate() const {
  auto bad = [](const char* name, double v, const char* range) {
    std::ostringstream s;
    s << "material '" << name << "' = " << v << " is invalid: expected " << range;
    throw std::invalid_argument(s.str());
  };
  if (!(youngs_modulus_pa > 0) || !std::isfinite(youngs_modulus_pa))
    bad("youngs_modulus_pa", youngs_modulus_pa, "a positive modulus in Pa, e.g. 2000");
  if (!(poisson_ratio > -1.0 && poisson_ratio < 0.5))
    bad("poisson_ratio", poisson_ratio, "a ratio in (-1, 0.5), e.g. 0.48");
  if (!(density_kg_per_m3 > 0) || !std::isfinite(density_kg_per_m3))
    bad("density_kg_per_m3", density_kg_per_m3, "a positive density in kg/m^3, e.g. 1000");
}

}  // namespace breast_sim::core
