// CalculiX reference: input deck, .dat reader, running ccx, result cache (reference/calculix.h).
// Deck format: CalculiX CrunchiX User's Manual, section 7 (*NODE, *ELEMENT, *NSET, *MATERIAL,
// *HYPERELASTIC, *ELASTIC, *DENSITY, *SOLID SECTION, *BOUNDARY, *STEP, *STATIC, *DLOAD GRAV,
// *NODE PRINT).

#include "breast_sim/core/reference/calculix.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <unordered_map>
#include <vector>

#include <unistd.h>

#include <nlohmann/json.hpp>

namespace breast_sim::core {
namespace fs = std::filesystem;

namespace {

/// Numbers in messages.
std::string num(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.17g", v);
  return buf;
}

/// Numbers in the deck: CalculiX reads a field of at most 20 characters ("*ERROR reading *NODE" /
/// "*STATIC" otherwise), so 14 significant digits ("-1.2345678901234e-05"): 1e-14 relative.
std::string par(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.14g", v);
  return buf;
}

std::string shellQuote(const std::string& s) {
  std::string q = "'";
  for (char c : s) q += c == '\'' ? std::string("'\\''") : std::string(1, c);
  return q + "'";
}

/// Writes `ids` (1-based) 16 per line, as *NSET / *ELSET data lines want (at most 16 per line).
void appendIdLines(std::string& s, const std::vector<long>& ids) {
  for (std::size_t i = 0; i < ids.size(); ++i) {
    s += std::to_string(ids[i]);
    s += (i + 1 == ids.size() || (i + 1) % 16 == 0) ? "\n" : ", ";
  }
}

constexpr std::uint32_t kCacheMagic = 0x42534352;  // "RCSB"

bool readCache(const fs::path& file, int num_nodes, Points& u) {
  std::ifstream f(file, std::ios::binary);
  if (!f) return false;
  std::uint32_t magic = 0;
  std::int64_t n = 0;
  f.read(reinterpret_cast<char*>(&magic), sizeof magic);
  f.read(reinterpret_cast<char*>(&n), sizeof n);
  if (!f || magic != kCacheMagic || n != num_nodes) return false;
  u.resize(num_nodes, 3);
  f.read(reinterpret_cast<char*>(u.data()), static_cast<std::streamsize>(sizeof(double) * 3 * num_nodes));
  return static_cast<bool>(f) && u.allFinite();
}

void writeCache(const fs::path& dir, const std::string& key, const Points& u, const nlohmann::json& meta) {
  fs::create_directories(dir);
  const fs::path tmp = dir / (key + ".u.tmp" + std::to_string(::getpid()));
  {
    std::ofstream f(tmp, std::ios::binary);
    const std::uint32_t magic = kCacheMagic;
    const std::int64_t n = u.rows();
    f.write(reinterpret_cast<const char*>(&magic), sizeof magic);
    f.write(reinterpret_cast<const char*>(&n), sizeof n);
    f.write(reinterpret_cast<const char*>(u.data()), static_cast<std::streamsize>(sizeof(double) * 3 * u.rows()));
    if (!f) throw std::runtime_error("reference cache: cannot write " + tmp.string());
  }
  fs::rename(tmp, dir / (key + ".u"));  // atomic: a concurrent reader sees the old file or the new one
  std::ofstream(dir / (key + ".json")) << meta.dump(2) << '\n';
}

}  // namespace

std::string referenceElementName(ReferenceElement e) { return e == ReferenceElement::kC3D10 ? "C3D10" : "C3D4"; }

ReferenceElement referenceElementFromName(const std::string& name) {
  std::string u = name;
  std::transform(u.begin(), u.end(), u.begin(), [](unsigned char c) { return static_cast<char>(std::toupper(c)); });
  if (u == "C3D4") return ReferenceElement::kC3D4;
  if (u == "C3D10") return ReferenceElement::kC3D10;
  throw std::invalid_argument("reference element '" + name + "': expected c3d4 or c3d10");
}

void CalculixLoadCase::validate() const {
  material.validate();
  if (!gravity_mps2.allFinite())
    throw std::invalid_argument("CalculixLoadCase.gravity_mps2 must be finite");
  if (!(initial_increment > 0 && initial_increment <= 1))
    throw std::invalid_argument("CalculixLoadCase.initial_increment = " + num(initial_increment) + ": expected (0, 1]");
  if (!(min_increment > 0 && min_increment <= initial_increment))
    throw std::invalid_argument("CalculixLoadCase.min_increment = " + num(min_increment) +
                                ": expected (0, initial_increment]");
  if (!(max_increment >= initial_increment && max_increment <= 1))
    throw std::invalid_argument("CalculixLoadCase.max_increment = " + num(max_increment) +
                                ": expected [initial_increment, 1]");
  for (Eigen::Index i = 0; i < modulus_factors.size(); ++i)
    if (!(modulus_factors[i] > 0 && std::isfinite(modulus_factors[i])))
      throw std::invalid_argument("CalculixLoadCase.modulus_factors[" + std::to_string(i) + "] = " +
                                  num(modulus_factors[i]) + ": expected a positive finite factor");
}

std::string calculixInputDeck(const TetMesh& mesh, const CalculixLoadCase& load) {
  load.validate();
  const int N = mesh.numNodes(), T = mesh.numTets();
  if (load.modulus_factors.size() != 0 && load.modulus_factors.size() != T)
    throw std::invalid_argument("CalculixLoadCase.modulus_factors has " + std::to_string(load.modulus_factors.size()) +
                                " entries; the mesh has " + std::to_string(T) + " elements (give one per element or none)");
  std::vector<int> fixed;
  if (!load.fixed_node_set.empty()) {
    if (!mesh.hasNodeSet(load.fixed_node_set)) {
      std::string have;
      for (const auto& kv : mesh.nodeSets()) have += (have.empty() ? "" : ", ") + kv.first;
      throw std::invalid_argument("CalculixLoadCase.fixed_node_set '" + load.fixed_node_set +
                                  "' is not a node set of the mesh (it has: " + have + ")");
    }
    fixed = mesh.nodeSet(load.fixed_node_set);
  }
  const bool quadratic = load.element == ReferenceElement::kC3D10;
  for (const CalculixNodeSupport& sup : load.node_supports) {
    if (sup.node < 0 || sup.node >= N)
      throw std::invalid_argument("CalculixLoadCase.node_supports: node " + std::to_string(sup.node) + " is not in [0, " +
                                  std::to_string(N) + ")");
    for (int a = 0; a < 3; ++a)
      if (!(sup.spring_n_per_m[a] >= 0) || !std::isfinite(sup.spring_n_per_m[a]))
        throw std::invalid_argument("CalculixLoadCase.node_supports: spring " + num(sup.spring_n_per_m[a]) +
                                    " N/m of node " + std::to_string(sup.node) + ": expected a finite stiffness >= 0");
  }
  if (quadratic && !load.node_supports.empty())
    throw std::invalid_argument("CalculixLoadCase.node_supports need C3D4 elements: with C3D10 the mid-edge nodes "
                                "would need springs and conditions of their own");

  std::string s;
  s.reserve(static_cast<std::size_t>(N) * 70 + static_cast<std::size_t>(T) * (quadratic ? 90 : 40) + 4096);
  s += "** breast_sim reference deck (SI units: m, Pa, kg/m^3, m/s^2)\n";
  s += "*NODE, NSET=NALL\n";
  const Points& X = mesh.nodes();
  for (int n = 0; n < N; ++n)
    s += std::to_string(n + 1) + ", " + par(X(n, 0)) + ", " + par(X(n, 1)) + ", " + par(X(n, 2)) + "\n";

  // C3D10: mid-edge nodes N+1, … in order of first appearance; CalculiX's node order is
  // corners 1–4, then edges 1-2, 2-3, 3-1, 1-4, 2-4, 3-4.
  static constexpr int kEdge[6][2] = {{0, 1}, {1, 2}, {2, 0}, {0, 3}, {1, 3}, {2, 3}};
  std::vector<std::array<long, 6>> mid;
  std::vector<long> fixed_mid;
  if (quadratic) {
    std::vector<char> is_fixed(N, 0);
    for (int n : fixed) is_fixed[n] = 1;
    std::unordered_map<std::uint64_t, long> edge_id;
    edge_id.reserve(static_cast<std::size_t>(T) * 2);
    mid.resize(T);
    long next = N + 1;
    for (int t = 0; t < T; ++t) {
      for (int e = 0; e < 6; ++e) {
        const int a = mesh.tets()(t, kEdge[e][0]), b = mesh.tets()(t, kEdge[e][1]);
        const std::uint64_t key = (static_cast<std::uint64_t>(std::min(a, b)) << 32) | static_cast<std::uint32_t>(std::max(a, b));
        auto [it, inserted] = edge_id.emplace(key, next);
        if (inserted) {
          const Eigen::Vector3d m = 0.5 * (X.row(a) + X.row(b)).transpose();
          s += std::to_string(next) + ", " + par(m.x()) + ", " + par(m.y()) + ", " + par(m.z()) + "\n";
          if (is_fixed[a] && is_fixed[b]) fixed_mid.push_back(next);
          ++next;
        }
        mid[t][e] = it->second;
      }
    }
  }

  // Elements grouped by modulus factor: one element set and one material per distinct factor.
  std::map<double, std::vector<long>> groups;
  for (int t = 0; t < T; ++t) groups[load.modulus_factors.size() ? load.modulus_factors[t] : 1.0].push_back(t + 1);
  int g = 0;
  std::vector<std::string> set_names;
  for (const auto& [factor, ids] : groups) {
    const std::string set = "E_M" + std::to_string(++g);
    set_names.push_back(set);
    s += std::string("*ELEMENT, TYPE=") + (quadratic ? "C3D10" : "C3D4") + ", ELSET=" + set + "\n";
    for (long id : ids) {
      const int t = static_cast<int>(id - 1);
      s += std::to_string(id);
      for (int k = 0; k < 4; ++k) s += ", " + std::to_string(mesh.tets()(t, k) + 1);
      if (quadratic)
        for (int e = 0; e < 6; ++e) s += ", " + std::to_string(mid[t][e]);
      s += "\n";
    }
  }
  s += "*ELSET, ELSET=EALL\n";
  for (const auto& name : set_names) s += name + "\n";
  if (!fixed.empty()) {
    s += "*NSET, NSET=FIXED\n";
    std::vector<long> ids;
    ids.reserve(fixed.size() + fixed_mid.size());
    for (int n : fixed) ids.push_back(n + 1);
    ids.insert(ids.end(), fixed_mid.begin(), fixed_mid.end());
    appendIdLines(s, ids);
  }
  // Materials: the neo-Hookean constants of E, ν (see the header).
  g = 0;
  for (const auto& [factor, ids] : groups) {
    (void)ids;
    const std::string mat = "M" + std::to_string(++g);
    ElasticMaterial m = load.material;
    m.youngs_modulus_pa *= factor;
    s += "*MATERIAL, NAME=" + mat + "\n";
    if (load.hyperelastic) {
      const double mu = m.lameMu(), K = m.youngs_modulus_pa / (3.0 * (1.0 - 2.0 * m.poisson_ratio));
      s += "*HYPERELASTIC, NEO HOOKE\n" + par(0.5 * mu) + ", " + par(2.0 / K) + "\n";
    } else {
      s += "*ELASTIC\n" + par(m.youngs_modulus_pa) + ", " + par(m.poisson_ratio) + "\n";
    }
    s += "*DENSITY\n" + par(m.density_kg_per_m3) + "\n";
    s += "*SOLID SECTION, ELSET=" + set_names[g - 1] + ", MATERIAL=" + mat + "\n";
  }
  // Node supports: grounded springs (SPRING1, numbered after the tetrahedra) and single DOFs.
  long spring_id = T;
  int spring_set = 0;
  for (const CalculixNodeSupport& sup : load.node_supports)
    for (int a = 0; a < 3; ++a) {
      if (!(sup.spring_n_per_m[a] > 0)) continue;
      const std::string set = "SPR" + std::to_string(++spring_set);
      s += "*ELEMENT, TYPE=SPRING1, ELSET=" + set + "\n" + std::to_string(++spring_id) + ", " +
           std::to_string(sup.node + 1) + "\n";
      s += "*SPRING, ELSET=" + set + "\n" + std::to_string(a + 1) + "\n" + par(sup.spring_n_per_m[a]) + "\n";
    }
  if (!fixed.empty()) s += "*BOUNDARY\nFIXED, 1, 3, 0.\n";
  bool any_dof = false;
  for (const CalculixNodeSupport& sup : load.node_supports)
    for (int a = 0; a < 3; ++a)
      if (sup.fixed[a]) {
        if (!any_dof) s += "*BOUNDARY\n";
        any_dof = true;
        s += std::to_string(sup.node + 1) + ", " + std::to_string(a + 1) + ", " + std::to_string(a + 1) + ", 0.\n";
      }
  s += std::string("*STEP") + (load.nlgeom ? ", NLGEOM" : "") + ", INC=10000\n";
  s += "*STATIC\n" + par(load.initial_increment) + ", 1., " + par(load.min_increment) + ", " + par(load.max_increment) + "\n";
  const double gn = load.gravity_mps2.norm();
  if (gn > 0) {
    const Eigen::Vector3d d = load.gravity_mps2 / gn;
    s += "*DLOAD\nEALL, GRAV, " + par(gn) + ", " + par(d.x()) + ", " + par(d.y()) + ", " + par(d.z()) + "\n";
  }
  s += "*NODE PRINT, NSET=NALL\nU\n*END STEP\n";
  return s;
}

void writeCalculixInput(const std::string& path, const TetMesh& mesh, const CalculixLoadCase& load) {
  const std::string deck = calculixInputDeck(mesh, load);
  std::ofstream f(path);
  f << deck;
  if (!f) throw std::runtime_error("cannot write the CalculiX deck " + path);
}

Points readCalculixDisplacements(const std::string& dat_path, int num_nodes, double* time_out) {
  std::ifstream f(dat_path);
  if (!f) throw std::runtime_error("cannot read the CalculiX result " + dat_path);
  Points u(num_nodes, 3), last;
  std::vector<char> seen, last_seen;
  bool in_block = false, any = false;
  double time = 0, last_time = 0;
  auto finish = [&] {
    if (in_block) {
      last = u;
      last_seen = seen;
      last_time = time;
      any = true;
    }
    in_block = false;
  };
  for (std::string line; std::getline(f, line);) {
    if (line.find("displacements (vx,vy,vz)") != std::string::npos) {
      finish();
      in_block = true;
      u.setZero();
      seen.assign(num_nodes, 0);
      const std::size_t at = line.find("time");
      time = at == std::string::npos ? 0.0 : std::strtod(line.c_str() + at + 4, nullptr);
      continue;
    }
    if (!in_block) continue;
    std::istringstream ls(line);
    long id;
    double x, y, z;
    if (!(ls >> id)) {
      if (line.find_first_not_of(" \t\r") == std::string::npos) continue;  // blank line inside/after a block
      finish();
      continue;
    }
    if (!(ls >> x >> y >> z)) throw std::runtime_error(dat_path + ": malformed displacement line '" + line + "'");
    if (id >= 1 && id <= num_nodes) {
      u.row(id - 1) << x, y, z;
      seen[id - 1] = 1;
    }
  }
  finish();
  if (!any) throw std::runtime_error(dat_path + ": no displacement block (*NODE PRINT U) found");
  for (int n = 0; n < num_nodes; ++n)
    if (!last_seen[n])
      throw std::runtime_error(dat_path + ": the last displacement block misses node " + std::to_string(n + 1));
  if (time_out) *time_out = last_time;
  return last;
}

std::string CalculixOptions::defaultReferenceCacheDir() {
  if (const char* d = std::getenv("BREAST_SIM_REFERENCE_CACHE"); d && *d) return d;
  if (const char* x = std::getenv("XDG_CACHE_HOME"); x && *x) return (fs::path(x) / "breast_sim" / "reference").string();
  if (const char* h = std::getenv("HOME"); h && *h) return (fs::path(h) / ".cache" / "breast_sim" / "reference").string();
  return (fs::temp_directory_path() / "breast_sim_reference").string();
}

bool calculixAvailable(const std::string& executable) {
  // `ccx -v` prints "This is Version 2.20" but exits with status 201: read what it prints.
  const std::string cmd = shellQuote(executable) + " -v 2>&1";
  FILE* p = ::popen(cmd.c_str(), "r");
  if (!p) return false;
  std::string text;
  char buf[256];
  while (std::fgets(buf, sizeof buf, p)) text += buf;
  ::pclose(p);
  return text.find("Version") != std::string::npos;
}

std::string referenceCacheKey(const std::string& deck_text) {
  std::uint64_t h = 1469598103934665603ULL;
  for (unsigned char c : deck_text) {
    h ^= c;
    h *= 1099511628211ULL;
  }
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(h));
  return buf;
}

CalculixResult solveWithCalculix(const TetMesh& mesh, const CalculixLoadCase& load, const CalculixOptions& options) {
  const std::string deck = calculixInputDeck(mesh, load);
  CalculixResult r;
  r.key = referenceCacheKey(deck);
  const int N = mesh.numNodes();
  const fs::path cache = options.cache_dir;
  if (!options.cache_dir.empty() && !options.refresh && readCache(cache / (r.key + ".u"), N, r.displacement_m)) {
    r.from_cache = true;
    std::ifstream meta(cache / (r.key + ".json"));
    if (meta) {
      try {
        const nlohmann::json j = nlohmann::json::parse(meta);
        r.solve_seconds = j.value("solve_seconds", 0.0);
        r.deck_nodes = j.value("deck_nodes", N);
      } catch (const std::exception&) {
      }
    }
    return r;
  }

  fs::path dir = options.work_dir;
  const bool own_dir = dir.empty();
  if (own_dir) {
    std::string tmpl = (fs::temp_directory_path() / "breast_sim_ccx_XXXXXX").string();
    if (!::mkdtemp(tmpl.data())) throw std::runtime_error("cannot create a temporary folder for CalculiX in " + fs::temp_directory_path().string());
    dir = tmpl;
  } else {
    fs::create_directories(dir);
  }
  const std::string job = "ref_" + r.key;
  {
    std::ofstream f(dir / (job + ".inp"));
    f << deck;
    if (!f) throw std::runtime_error("cannot write the CalculiX deck in " + dir.string());
  }
  std::string env;
  if (options.threads > 0)
    env = "OMP_NUM_THREADS=" + std::to_string(options.threads) + " CCX_NPROC_EQUATION_SOLVER=" +
          std::to_string(options.threads) + " CCX_NPROC_RESULTS=" + std::to_string(options.threads) + " ";
  // CalculiX's OpenMP threads wait as ours do: a short spin unless the user chose (src/openmp_wait).
  for (const char* name : {"OMP_WAIT_POLICY", "GOMP_SPINCOUNT"})
    if (const char* value = std::getenv(name)) env += std::string(name) + "=" + shellQuote(value) + " ";
  const std::string cmd = "cd " + shellQuote(dir.string()) + " && " + env + shellQuote(options.executable) + " -i " + job +
                          " > " + job + ".log 2>&1";
  const auto t0 = std::chrono::steady_clock::now();
  const int status = std::system(cmd.c_str());
  r.solve_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const fs::path log = dir / (job + ".log");
  std::string log_text;
  {
    std::ifstream lf(log);
    std::stringstream ss;
    ss << lf.rdbuf();
    log_text = ss.str();
  }
  const std::size_t err = log_text.find("*ERROR");
  if (status != 0 || err != std::string::npos) {
    std::string what = err != std::string::npos ? log_text.substr(err, log_text.find('\n', err) - err) : "exit status " + std::to_string(status);
    throw std::runtime_error("CalculiX failed (" + what + "); deck and log in " + dir.string() + " (" + job + ".inp, " + job + ".log)");
  }
  double time = 0.0;
  r.displacement_m = readCalculixDisplacements((dir / (job + ".dat")).string(), N, &time);
  if (std::abs(time - 1.0) > 1e-6)
    throw std::runtime_error("CalculiX stopped at load fraction " + num(time) + " of 1 (no convergence); deck and log in " +
                             dir.string());
  r.deck_nodes = N;
  if (load.element == ReferenceElement::kC3D10) {
    // The deck's node lines: everything between its two header lines and the first *ELEMENT.
    r.deck_nodes = static_cast<int>(std::count(deck.begin(), deck.begin() + static_cast<long>(deck.find("*ELEMENT")), '\n')) - 2;
  }
  r.work_dir = dir.string();
  if (!options.cache_dir.empty()) {
    nlohmann::json meta = {{"key", r.key},
                           {"nodes", N},
                           {"deck_nodes", r.deck_nodes},
                           {"elements", mesh.numTets()},
                           {"element_type", referenceElementName(load.element)},
                           {"youngs_modulus_pa", load.material.youngs_modulus_pa},
                           {"poisson_ratio", load.material.poisson_ratio},
                           {"density_kg_per_m3", load.material.density_kg_per_m3},
                           {"gravity_mps2", {load.gravity_mps2.x(), load.gravity_mps2.y(), load.gravity_mps2.z()}},
                           {"hyperelastic", load.hyperelastic},
                           {"nlgeom", load.nlgeom},
                           {"solve_seconds", r.solve_seconds},
                           {"max_displacement_m", r.displacement_m.rowwise().norm().maxCoeff()}};
    writeCache(cache, r.key, r.displacement_m, meta);
  }
  if (own_dir && !options.keep_files) {
    std::error_code ec;
    fs::remove_all(dir, ec);
    r.work_dir.clear();
  }
  return r;
}

}  // namespace breast_sim::core
