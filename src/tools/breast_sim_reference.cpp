// breast_sim_reference: the independent CalculiX reference of a case. Builds the case's model (the
// same mesher and meshing options as breast_sim_run), writes it with its material and gravity load
// as a CalculiX deck (neo-Hookean, NLGEOM; C3D4 or C3D10), runs ccx — or takes the cached result of
// the identical deck — and writes the reference displacement field (reference/calculix.h).
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <stdexcept>
#include <string>

#include <nlohmann/json.hpp>

#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/reference/calculix.h"
#include "breast_sim/core/reference/reference_case.h"

namespace fs = std::filesystem;
using namespace breast_sim::core;

namespace {

const char* kUsage = R"(usage: breast_sim_reference --case CASE.yaml --out DIR [--target-elements N] [--element c3d4|c3d10]
                            [--load supine|hanging] [--poisson-ratio NU] [--youngs-modulus-pa E]
                            [--cache DIR | --no-cache] [--refresh] [--threads N] [--keep]

Solves the case's gravity load with CalculiX (neo-Hookean, C10 = mu/2, D1 = 2/K from the case's E and
nu, NLGEOM, chest wall fixed) on the case's model and writes to DIR:
  reference.inp          the CalculiX deck (SI units)
  reference.vtu          the model with the reference displacement (displacement_mm)
  reference.json         key, element type, material, load, solve time, largest displacement
Results are cached by a hash of the deck (mesh, material, load): a rerun takes seconds.
Options:
  --case FILE            YAML case file (see config/phantom_default.yaml)
  --out DIR              output folder (created)
  --target-elements N    overrides meshing.target_elements of the case
  --element TYPE         c3d4 (our linear tetrahedra, default) or c3d10 (quadratic, no locking)
  --load NAME            supine: g_supine - g_prone (default); hanging: g_prone
  --poisson-ratio NU     overrides simulation.poisson_ratio
  --youngs-modulus-pa E  overrides simulation.youngs_modulus_pa
  --cache DIR            result cache (default $BREAST_SIM_REFERENCE_CACHE or ~/.cache/breast_sim/reference)
  --no-cache             always run ccx, store nothing
  --refresh              run ccx even when cached, and replace the cached result
  --threads N            threads for ccx (OMP_NUM_THREADS); default: inherit
  --keep                 keep ccx's work folder (its path is printed)
)";

int intValue(const std::string& k, const std::string& v) {
  try {
    std::size_t used = 0;
    const int x = std::stoi(v, &used);
    if (used == v.size() && x > 0) return x;
  } catch (...) {
  }
  throw std::invalid_argument(k + " '" + v + "': expected a positive whole number");
}

double doubleValue(const std::string& k, const std::string& v) {
  try {
    std::size_t used = 0;
    const double x = std::stod(v, &used);
    if (used == v.size()) return x;
  } catch (...) {
  }
  throw std::invalid_argument(k + " '" + v + "': expected a number");
}

}  // namespace

int main(int argc, char** argv) {
  try {
    std::string case_file, out_dir, element = "c3d4", load_name = "supine";
    int target = 0;
    double nu = -2, youngs = -1;
    CalculixOptions opt;
    for (int i = 1; i < argc; ++i) {
      const std::string k = argv[i];
      auto value = [&]() -> std::string {
        if (i + 1 >= argc) throw std::invalid_argument("option " + k + " needs a value\n" + kUsage);
        return argv[++i];
      };
      if (k == "--case") case_file = value();
      else if (k == "--out") out_dir = value();
      else if (k == "--target-elements") target = intValue(k, value());
      else if (k == "--element") element = value();
      else if (k == "--load") load_name = value();
      else if (k == "--poisson-ratio") nu = doubleValue(k, value());
      else if (k == "--youngs-modulus-pa") youngs = doubleValue(k, value());
      else if (k == "--cache") opt.cache_dir = value();
      else if (k == "--no-cache") opt.cache_dir.clear();
      else if (k == "--refresh") opt.refresh = true;
      else if (k == "--threads") opt.threads = intValue(k, value());
      else if (k == "--keep") opt.keep_files = true;
      else if (k == "-h" || k == "--help") {
        std::cout << kUsage;
        return 0;
      } else throw std::invalid_argument("unknown option '" + k + "'\n" + kUsage);
    }
    if (case_file.empty() || out_dir.empty()) throw std::invalid_argument(std::string("--case and --out are required\n") + kUsage);

    ModelCase c = loadModelCase(case_file);
    if (target > 0) c.meshing.target_elements = target;
    SimulationSettings s = loadSimulationSettings(case_file);
    if (nu > -2) s.material.poisson_ratio = nu;
    if (youngs > 0) s.material.youngs_modulus_pa = youngs;
    s.validate();
    const GravityLoadCase which = gravityLoadCaseFromName(load_name);
    const ReferenceElement type = referenceElementFromName(element);
    // The mesh is cached with the result: meshing is not repeatable run to run (reference_case.h).
    bool mesh_cached = false;
    const SimulationModel m = cachedSimulationModel(c, opt.cache_dir, &mesh_cached);
    const Eigen::Vector3d g = gravityLoad(c, which, s.gravity_mps2);
    const CalculixLoadCase load = referenceLoadCase(s, m.mesh, g, type);  // per-tissue moduli as element sets

    fs::create_directories(out_dir);
    const fs::path out(out_dir);
    writeCalculixInput((out / "reference.inp").string(), m.mesh, load);
    std::printf("%s: %d elements, %d nodes%s; %s, E = %.0f Pa, nu = %.3f, load %s (%.3f, %.3f, %.3f) m/s^2\n", c.name.c_str(),
                m.mesh.numTets(), m.mesh.numNodes(), mesh_cached ? " (mesh from the cache)" : "", referenceElementName(type).c_str(), s.material.youngs_modulus_pa,
                s.material.poisson_ratio, load_name.c_str(), g.x(), g.y(), g.z());
    if (!calculixAvailable(opt.executable))
      throw std::runtime_error("CalculiX ('" + opt.executable + "') is not installed: apt-get install calculix-ccx (scripts/install_deps.sh)");
    std::fflush(stdout);
    const CalculixResult r = solveWithCalculix(m.mesh, load, opt);
    const double umax = r.displacement_m.rowwise().norm().maxCoeff();
    std::printf("reference %s: %s, ccx %.1f s, %d deck nodes, largest displacement %.3f mm\n", r.key.c_str(),
                r.from_cache ? "from the cache" : "computed", r.solve_seconds, r.deck_nodes, 1e3 * umax);
    if (!r.work_dir.empty()) std::printf("ccx work folder: %s\n", r.work_dir.c_str());

    MeshFields f;
    f.point_data.push_back({"displacement_mm", Eigen::MatrixXd(r.displacement_m * 1e3), false});
    writeTetMesh((out / "reference.vtu").string(), m.mesh, f);
    nlohmann::json j = {{"case", c.name},
                        {"key", r.key},
                        {"from_cache", r.from_cache},
                        {"element_type", referenceElementName(type)},
                        {"elements", m.mesh.numTets()},
                        {"nodes", m.mesh.numNodes()},
                        {"deck_nodes", r.deck_nodes},
                        {"youngs_modulus_pa", s.material.youngs_modulus_pa},
                        {"poisson_ratio", s.material.poisson_ratio},
                        {"load", load_name},
                        {"gravity_mps2", {g.x(), g.y(), g.z()}},
                        {"ccx_seconds", r.solve_seconds},
                        {"max_displacement_mm", 1e3 * umax}};
    std::ofstream(out / "reference.json") << j.dump(2) << '\n';
    return 0;
  } catch (const std::invalid_argument& e) {
    std::fprintf(stderr, "breast_sim_reference: %s\n", e.what());
    return 2;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "breast_sim_reference: %s\n", e.what());
    return 1;
  }
}
