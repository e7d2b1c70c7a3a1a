// Tests of the CalculiX reference (deck, .dat reader, cache, runs against our FEM), the error
// metrics and the model choice. The CalculiX runs are tiny (a 96-element column, < 1 s each); they
// are skipped only when no ccx binary is installed (scripts/install_deps.sh installs calculix-ccx).

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>
#include <regex>
#include <set>

#include <unistd.h>

#include <gtest/gtest.h>

#include "breast_sim/core/fem/corotated_tet_fem.h"
#include "breast_sim/core/fem/dynamic_simulator.h"
#include "breast_sim/core/fem/equilibrium.h"
#include "breast_sim/core/fem/simulation_settings.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/reference/calculix.h"
#include "breast_sim/core/reference/error_metrics.h"
#include "breast_sim/core/reference/model_choice.h"
#include "breast_sim/core/reference/reference_case.h"
#include "breast_sim/core/solver/cholmod_solver.h"
#include "../../src/core/util/closest_point.h"

using namespace breast_sim::core;
namespace fs = std::filesystem;

namespace {

fs::path tempDir(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("breast_sim_test_reference_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(d);
  fs::create_directories(d);
  return d;
}

/// A column 6 cm long along x, 2 × 2 cm, fixed at x = 0 ("x_min" → "chest_wall"), 96 elements.
TetMesh column() {
  TetMesh m = makeBoxMesh({4, 2, 2}, {0.06, 0.02, 0.02});
  m.setNodeSet("chest_wall", m.nodeSet("x_min"));
  return m;
}

/// Our FEM settled tightly (CHOLMOD, long steps): static equilibrium of the linear or co-rotated model.
Points ourStatic(const TetMesh& m, const ElasticMaterial& mat, const Eigen::Vector3d& g, bool corotated) {
  DynamicsParams p;
  p.gravity_mps2 = g;
  auto fem = std::make_unique<CorotatedTetFem>(m, mat);
  fem->setCorotated(corotated);
  DynamicSimulator sim(m, std::move(fem), mat, p, std::make_unique<CholmodSolver>());
  sim.fixNodes(m.nodeSet("chest_wall"));
  SettleOptions o;
  o.time_step_s = 10.0;
  o.increment_tolerance_m = 1e-13;
  o.consecutive_steps = 2;
  o.max_steps = 400;
  EXPECT_TRUE(settle(sim, o).settled);
  return sim.displacement();
}

double maxRowNorm(const Points& p) { return p.rowwise().norm().maxCoeff(); }

}  // namespace

TEST(CalculixDeck, ParsesBackAsTheSameMeshAndHoldsTheNeoHookeanConstants) {
  const TetMesh m = column();
  CalculixLoadCase load;
  load.material.youngs_modulus_pa = 2000;
  load.material.poisson_ratio = 0.45;
  load.material.density_kg_per_m3 = 1050;
  load.gravity_mps2 = {0, -9.81, 0};
  const fs::path dir = tempDir("deck");
  const std::string path = (dir / "deck.inp").string();
  writeCalculixInput(path, m, load);
  // The project's Abaqus reader reads it back: same nodes (SI), elements and the fixed set.
  const TetMesh back = readAbaqusInp(path, 1.0);
  ASSERT_EQ(back.numNodes(), m.numNodes());
  ASSERT_EQ(back.numTets(), m.numTets());
  EXPECT_LT((back.nodes() - m.nodes()).cwiseAbs().maxCoeff(), 1e-15);  // 14 significant digits of 6 cm
  EXPECT_EQ(back.tets(), m.tets());
  std::vector<int> fixed = back.nodeSet("FIXED"), expect = m.nodeSet("chest_wall");
  std::sort(fixed.begin(), fixed.end());
  std::sort(expect.begin(), expect.end());
  EXPECT_EQ(fixed, expect);

  const std::string deck = calculixInputDeck(m, load);
  std::smatch mt;
  ASSERT_TRUE(std::regex_search(deck, mt, std::regex(R"(\*HYPERELASTIC, NEO HOOKE\n([^,]+), ([^\n]+)\n)")));
  const double mu = 2000 / (2 * 1.45), K = 2000 / (3 * (1 - 0.9));
  EXPECT_NEAR(std::stod(mt[1]), mu / 2, 1e-9 * mu);
  EXPECT_NEAR(std::stod(mt[2]), 2 / K, 1e-12);
  EXPECT_NE(deck.find("*DENSITY\n1050\n"), std::string::npos);
  ASSERT_TRUE(std::regex_search(deck, mt, std::regex(R"(\*DLOAD\nEALL, GRAV, ([^,]+), ([^,]+), ([^,]+), ([^\n]+)\n)")));
  EXPECT_DOUBLE_EQ(std::stod(mt[1]), 9.81);
  EXPECT_DOUBLE_EQ(std::stod(mt[2]), 0.0);
  EXPECT_DOUBLE_EQ(std::stod(mt[3]), -1.0);
  EXPECT_DOUBLE_EQ(std::stod(mt[4]), 0.0);
  EXPECT_NE(deck.find("*STEP, NLGEOM"), std::string::npos);
  EXPECT_NE(deck.find("*BOUNDARY\nFIXED, 1, 3, 0.\n"), std::string::npos);
  fs::remove_all(dir);
}

TEST(CalculixDeck, QuadraticElementsAddOneNodePerEdgeAndFixWallEdges) {
  const TetMesh m = column();
  CalculixLoadCase load;
  load.element = ReferenceElement::kC3D10;
  const std::string deck = calculixInputDeck(m, load);
  // Unique edges of the mesh, and those with both ends fixed.
  std::set<std::pair<int, int>> edges;
  std::set<int> fixed(m.nodeSet("chest_wall").begin(), m.nodeSet("chest_wall").end());
  for (int t = 0; t < m.numTets(); ++t)
    for (int a = 0; a < 4; ++a)
      for (int b = a + 1; b < 4; ++b)
        edges.insert({std::min(m.tets()(t, a), m.tets()(t, b)), std::max(m.tets()(t, a), m.tets()(t, b))});
  int fixed_edges = 0;
  for (const auto& e : edges) fixed_edges += fixed.count(e.first) && fixed.count(e.second);
  const std::size_t nodes_begin = deck.find("*NODE"), elem = deck.find("*ELEMENT");
  const long node_lines = std::count(deck.begin() + static_cast<long>(nodes_begin), deck.begin() + static_cast<long>(elem), '\n') - 1;
  EXPECT_EQ(node_lines, m.numNodes() + static_cast<long>(edges.size()));
  EXPECT_NE(deck.find("TYPE=C3D10"), std::string::npos);
  const std::size_t fs0 = deck.find("*NSET, NSET=FIXED\n"), fs1 = deck.find("*MATERIAL");
  const std::string fset = deck.substr(fs0 + 18, fs1 - fs0 - 18);
  const long fixed_ids = std::count(fset.begin(), fset.end(), ',') + std::count(fset.begin(), fset.end(), '\n');
  EXPECT_EQ(fixed_ids, static_cast<long>(fixed.size()) + fixed_edges);
}

TEST(CalculixDeck, RejectsBadInputNamingIt) {
  const TetMesh m = column();
  CalculixLoadCase load;
  load.fixed_node_set = "no_such_set";
  try {
    calculixInputDeck(m, load);
    FAIL() << "expected std::invalid_argument";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("no_such_set"), std::string::npos);
    EXPECT_NE(std::string(e.what()).find("chest_wall"), std::string::npos);
  }
  load.fixed_node_set = "chest_wall";
  load.modulus_factors = Eigen::VectorXd::Ones(3);
  EXPECT_THROW(calculixInputDeck(m, load), std::invalid_argument);
  load.modulus_factors = Eigen::VectorXd();
  load.max_increment = 2;
  EXPECT_THROW(calculixInputDeck(m, load), std::invalid_argument);
}

TEST(CalculixDeck, ModulusFactorsMakeOneMaterialPerDistinctFactor) {
  const TetMesh m = column();
  CalculixLoadCase load;
  load.material.youngs_modulus_pa = 1000;
  load.modulus_factors = Eigen::VectorXd::Ones(m.numTets());
  for (int t = 0; t < 10; ++t) load.modulus_factors[t] = 5.0;
  const std::string deck = calculixInputDeck(m, load);
  EXPECT_NE(deck.find("*MATERIAL, NAME=M1"), std::string::npos);
  EXPECT_NE(deck.find("*MATERIAL, NAME=M2"), std::string::npos);
  EXPECT_EQ(deck.find("*MATERIAL, NAME=M3"), std::string::npos);
  EXPECT_NE(deck.find("*SOLID SECTION, ELSET=E_M2, MATERIAL=M2"), std::string::npos);
  // Cache keys: equal for equal decks, different when the material changes.
  CalculixLoadCase other = load;
  EXPECT_EQ(referenceCacheKey(calculixInputDeck(m, other)), referenceCacheKey(deck));
  other.material.poisson_ratio = 0.4;
  EXPECT_NE(referenceCacheKey(calculixInputDeck(m, other)), referenceCacheKey(deck));
}

TEST(CalculixDat, ReadsTheLastBlock) {
  const fs::path dir = tempDir("dat");
  const std::string path = (dir / "r.dat").string();
  std::ofstream(path) << "\n displacements (vx,vy,vz) for set NALL and time  0.5000000E+00\n\n"
                         "         1  1.000000E-03  0.000000E+00  0.000000E+00\n"
                         "         2  2.000000E-03  0.000000E+00  0.000000E+00\n"
                         "         3  9.000000E-03  0.000000E+00  0.000000E+00\n"
                         "\n displacements (vx,vy,vz) for set NALL and time  0.1000000E+01\n\n"
                         "         1 -1.500000E-03  2.000000E-04  3.000000E-05\n"
                         "         2  4.000000E-03  0.000000E+00 -1.000000E+00\n"
                         "         3  9.000000E-03  0.000000E+00  0.000000E+00\n";
  double time = 0;
  const Points u = readCalculixDisplacements(path, 2, &time);
  EXPECT_DOUBLE_EQ(time, 1.0);
  EXPECT_DOUBLE_EQ(u(0, 0), -1.5e-3);
  EXPECT_DOUBLE_EQ(u(0, 2), 3e-5);
  EXPECT_DOUBLE_EQ(u(1, 2), -1.0);
  EXPECT_THROW(readCalculixDisplacements(path, 4), std::runtime_error);  // node 4 missing
  std::ofstream(path) << "nothing here\n";
  EXPECT_THROW(readCalculixDisplacements(path, 2), std::runtime_error);
  fs::remove_all(dir);
}

// The slow reference for the whole chain (deck, units, load, support, reader): CalculiX's linear
// analysis of C3D4 elements is exactly our linear (not co-rotated) FEM at equilibrium.
TEST(CalculixRun, LinearColumnUnderGravityMatchesOurLinearFem) {
  if (!calculixAvailable()) GTEST_SKIP() << "ccx not installed (apt-get install calculix-ccx)";
  const TetMesh m = column();
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 3000;
  mat.poisson_ratio = 0.3;
  const Eigen::Vector3d g(0.3, -9.81, 1.0);  // bending plus a little axial load
  CalculixLoadCase load;
  load.material = mat;
  load.gravity_mps2 = g;
  load.hyperelastic = false;
  load.nlgeom = false;
  CalculixOptions opt;
  opt.cache_dir = tempDir("cache_linear").string();
  const CalculixResult ref = solveWithCalculix(m, load, opt);
  EXPECT_FALSE(ref.from_cache);
  const Points ours = ourStatic(m, mat, g, /*corotated=*/false);
  const double scale = maxRowNorm(ref.displacement_m);
  EXPECT_GT(scale, 1e-3);  // a real load: millimetres
  // ccx prints 7 significant digits; our settling stops at 1e-13 m increments.
  EXPECT_LT(maxRowNorm(ours - ref.displacement_m), 1e-5 * scale) << "max displacement " << scale;

  // The second run comes from the cache, bit for bit.
  const CalculixResult again = solveWithCalculix(m, load, opt);
  EXPECT_TRUE(again.from_cache);
  EXPECT_EQ(again.key, ref.key);
  EXPECT_EQ((again.displacement_m - ref.displacement_m).cwiseAbs().maxCoeff(), 0.0);
  fs::remove_all(opt.cache_dir);
}

// Neo-Hookean with finite strain under a small load is linear elasticity to first order: our
// co-rotated model and CalculiX's NLGEOM neo-Hooke agree to the size of the strain (0.3 % here).
TEST(CalculixRun, NeoHookeanUnderSmallLoadMatchesOurCorotatedFem) {
  if (!calculixAvailable()) GTEST_SKIP() << "ccx not installed (apt-get install calculix-ccx)";
  const TetMesh m = column();
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 2e5;  // stiff: the tip moves ~0.1 mm on a 6 cm column
  mat.poisson_ratio = 0.45;
  const Eigen::Vector3d g(0, -9.81, 0);
  CalculixLoadCase load;
  load.material = mat;
  load.gravity_mps2 = g;
  CalculixOptions opt;
  opt.cache_dir = "";  // no cache
  const CalculixResult ref = solveWithCalculix(m, load, opt);
  const Points ours = ourStatic(m, mat, g, /*corotated=*/true);
  const double scale = maxRowNorm(ref.displacement_m);
  EXPECT_GT(scale, 1e-5);
  EXPECT_LT(scale, 1e-3);
  EXPECT_LT(maxRowNorm(ours - ref.displacement_m), 1e-2 * scale) << "max displacement " << scale;

  // Quadratic tetrahedra on the same corners are softer in bending than linear ones (which lock
  // in bending and, as ν → 0.5, in volume): their tip moves more, by a bounded amount.
  load.element = ReferenceElement::kC3D10;
  const CalculixResult quad = solveWithCalculix(m, load, opt);
  const double qscale = maxRowNorm(quad.displacement_m);
  EXPECT_GT(qscale, 1.05 * scale);
  EXPECT_LT(qscale, 3.0 * scale);
}

// Per-tissue moduli (simulation.tissue_youngs_modulus_pa) reach both models: the column's far half
// is region 4 (lesion) at 10 E0. CalculiX's linear analysis of the two-material deck (two element
// sets, two *MATERIAL) equals our linear FEM with the same per-element moduli, and differs clearly
// from the one-material answer; a lesion modulus equal to E0 gives the one-material deck's answer.
TEST(CalculixRun, TwoMaterialColumnMatchesOurLinearFemWithPerTissueModuli) {
  if (!calculixAvailable()) GTEST_SKIP() << "ccx not installed (apt-get install calculix-ccx)";
  const TetMesh base = column();
  std::vector<int> labels(base.numTets(), 1);
  for (int t = 0; t < base.numTets(); ++t) {
    double cx = 0;
    for (int k = 0; k < 4; ++k) cx += 0.25 * base.nodes()(base.tets()(t, k), 0);
    if (cx > 0.03) labels[t] = 4;
  }
  TetMesh m(base.nodes(), base.tets(), labels);
  m.setNodeSet("chest_wall", base.nodeSet("x_min"));
  SimulationSettings s;
  s.material.youngs_modulus_pa = 3000;
  s.material.poisson_ratio = 0.3;
  s.region_youngs_modulus_pa = {{4, 30000.0}};
  const Eigen::Vector3d g(0.3, -9.81, 1.0);
  EXPECT_THROW(referenceLoadCase(s, g), std::invalid_argument);  // moduli need the mesh
  CalculixLoadCase load = referenceLoadCase(s, m, g);
  ASSERT_EQ(load.modulus_factors.size(), m.numTets());
  load.hyperelastic = false;
  load.nlgeom = false;
  const std::string deck = calculixInputDeck(m, load);
  EXPECT_NE(deck.find("*MATERIAL, NAME=M2"), std::string::npos);
  EXPECT_EQ(deck.find("*MATERIAL, NAME=M3"), std::string::npos);
  CalculixOptions opt;
  opt.cache_dir = "";
  const CalculixResult ref = solveWithCalculix(m, load, opt);

  DynamicsParams p;
  p.gravity_mps2 = g;
  auto fem = std::make_unique<CorotatedTetFem>(m, s.material);
  fem->setCorotated(false);
  fem->setElementYoungsModuli(elementYoungsModuli(m, s));
  DynamicSimulator sim(m, std::move(fem), s.material, p, std::make_unique<CholmodSolver>());
  sim.fixNodes(m.nodeSet("chest_wall"));
  SettleOptions o;
  o.time_step_s = 10.0;
  o.increment_tolerance_m = 1e-13;
  o.max_steps = 400;
  ASSERT_TRUE(settle(sim, o).settled);
  const double scale = maxRowNorm(ref.displacement_m);
  EXPECT_GT(scale, 1e-4);
  EXPECT_LT(maxRowNorm(sim.displacement() - ref.displacement_m), 1e-5 * scale) << "max displacement " << scale;
  const Points uniform = ourStatic(m, s.material, g, /*corotated=*/false);
  // The stiff far half matters (the bending moment is largest at the clamp): measured 12 % of the
  // tip deflection, against the 1e-5 agreement above.
  EXPECT_GT(maxRowNorm(uniform - ref.displacement_m), 0.05 * scale);

  // Two labels of equal modulus: the same deck as one material (one *MATERIAL), the same answer.
  SimulationSettings same = s;
  same.region_youngs_modulus_pa = {{4, 3000.0}, {1, 3000.0}};
  CalculixLoadCase one = referenceLoadCase(same, m, g);
  one.hyperelastic = false;
  one.nlgeom = false;
  const std::string one_deck = calculixInputDeck(m, one);
  EXPECT_EQ(one_deck.find("*MATERIAL, NAME=M2"), std::string::npos);
  SimulationSettings none = s;
  none.region_youngs_modulus_pa.clear();
  CalculixLoadCase plain = referenceLoadCase(none, g);
  plain.hyperelastic = false;
  plain.nlgeom = false;
  EXPECT_EQ(one_deck, calculixInputDeck(m, plain));
}

// Node supports (a wall the tissue slides on, reference for "+ sliding"): the column's free end
// x = L hangs on grounded springs along y (SPRING1) with z held (a single-DOF *BOUNDARY). CalculiX's
// linear answer equals our linear FEM with the same springs as DynamicSimulator node springs (z held
// by a spring 1e6 times stiffer), and the springs carry load (the free column sags twice as far).
TEST(CalculixRun, NodeSupportsGiveSpringsAndSingleDofsAsOurNodeSprings) {
  if (!calculixAvailable()) GTEST_SKIP() << "ccx not installed (apt-get install calculix-ccx)";
  const TetMesh m = column();
  ElasticMaterial mat;
  mat.youngs_modulus_pa = 3000;
  mat.poisson_ratio = 0.3;
  const Eigen::Vector3d g(0.0, -9.81, 2.0);
  const double k = 0.5;  // [N/m] per node
  CalculixLoadCase load;
  load.material = mat;
  load.gravity_mps2 = g;
  load.hyperelastic = false;
  load.nlgeom = false;
  const std::vector<int> end = m.nodeSet("x_max");
  for (int n : end) {
    CalculixNodeSupport sup;
    sup.node = n;
    sup.fixed = {{false, false, true}};
    sup.spring_n_per_m = Eigen::Vector3d(0, k, 0);
    load.node_supports.push_back(sup);
  }
  const std::string deck = calculixInputDeck(m, load);
  EXPECT_NE(deck.find("TYPE=SPRING1"), std::string::npos);
  EXPECT_NE(deck.find(std::to_string(end[0] + 1) + ", 3, 3, 0."), std::string::npos);
  CalculixOptions opt;
  opt.cache_dir = "";
  const CalculixResult ref = solveWithCalculix(m, load, opt);

  DynamicsParams p;
  p.gravity_mps2 = g;
  auto fem = std::make_unique<CorotatedTetFem>(m, mat);
  fem->setCorotated(false);
  DynamicSimulator sim(m, std::move(fem), mat, p, std::make_unique<CholmodSolver>());
  sim.fixNodes(m.nodeSet("chest_wall"));
  std::vector<Eigen::Matrix3d> K(end.size(), Eigen::Vector3d(0, k, 1e6 * k).asDiagonal().toDenseMatrix());
  Points anchors(static_cast<Eigen::Index>(end.size()), 3);
  for (size_t i = 0; i < end.size(); ++i) anchors.row(static_cast<Eigen::Index>(i)) = m.nodes().row(end[i]);
  sim.setNodeSprings(end, K, anchors);
  SettleOptions o;
  o.time_step_s = 10.0;
  o.increment_tolerance_m = 1e-13;
  o.max_steps = 400;
  ASSERT_TRUE(settle(sim, o).settled);
  const double scale = maxRowNorm(ref.displacement_m);
  EXPECT_GT(scale, 1e-4);
  EXPECT_LT(maxRowNorm(sim.displacement() - ref.displacement_m), 1e-4 * scale) << "max displacement " << scale;
  double end_z = 0;
  for (int n : end) end_z = std::max(end_z, std::abs(ref.displacement_m(n, 2)));
  EXPECT_EQ(end_z, 0.0);
  CalculixLoadCase free = load;
  free.node_supports.clear();
  EXPECT_GT(maxRowNorm(solveWithCalculix(m, free, opt).displacement_m), 2.0 * scale);

  CalculixLoadCase bad = load;
  bad.element = ReferenceElement::kC3D10;
  EXPECT_THROW(calculixInputDeck(m, bad), std::invalid_argument);  // supports need C3D4
  bad = load;
  bad.node_supports[0].node = m.numNodes();
  EXPECT_THROW(calculixInputDeck(m, bad), std::invalid_argument);
  bad = load;
  bad.node_supports[0].spring_n_per_m.y() = -1;
  EXPECT_THROW(calculixInputDeck(m, bad), std::invalid_argument);
}

TEST(CalculixRun, ReportsAFailedRunWithItsFolder) {
  if (!calculixAvailable()) GTEST_SKIP() << "ccx not installed (apt-get install calculix-ccx)";
  CalculixOptions opt;
  opt.cache_dir = "";
  opt.executable = "/bin/false";
  const TetMesh m = column();
  EXPECT_THROW(solveWithCalculix(m, CalculixLoadCase{}, opt), std::runtime_error);
}

TEST(ErrorMetrics, SameMeshNodalErrorsOfAKnownOffset) {
  const TetMesh m = column();
  Points u = Points::Zero(m.numNodes(), 3), ref = u;
  std::vector<char> fixed(m.numNodes(), 0);
  for (int n : m.nodeSet("chest_wall")) fixed[n] = 1;
  int free = 0;
  for (int n = 0; n < m.numNodes(); ++n) {
    u.row(n) << 0.0, -1e-3 * m.nodes()(n, 0) / 0.06, 0.0;
    ref.row(n) = u.row(n);
    if (!fixed[n]) {
      ref(n, 2) += 2e-3;  // 2 mm off, everywhere but the wall
      ++free;
    }
  }
  const DisplacementErrors e = compareDisplacements(m, u, m, ref);
  EXPECT_EQ(e.nodes_compared, free);
  EXPECT_NEAR(e.mean_mm, 2.0, 1e-12);
  EXPECT_NEAR(e.p95_mm, 2.0, 1e-12);
  EXPECT_NEAR(e.max_mm, 2.0, 1e-12);
  EXPECT_NEAR(e.max_displacement_mm, 1.0, 1e-12);
  // A lesion in the middle of the column: its error is the offset.
  Points lesion(1, 3);
  lesion << 0.03, 0.01, 0.01;
  const DisplacementErrors el = compareDisplacements(m, u, m, ref, lesion);
  ASSERT_EQ(el.lesion_error_mm.size(), 1u);
  EXPECT_NEAR(el.lesion_error_mm[0], 2.0, 1e-9);
  EXPECT_THROW(compareDisplacements(m, u.topRows(3), m, ref), std::invalid_argument);
}

TEST(ErrorMetrics, AcrossMeshesALinearFieldTransfersExactly) {
  TetMesh coarse = makeBoxMesh({3, 2, 2}, {0.06, 0.02, 0.02});
  coarse.setNodeSet("chest_wall", coarse.nodeSet("x_min"));
  TetMesh fine = makeBoxMesh({9, 5, 4}, {0.06, 0.02, 0.02});
  auto field = [](const Points& x) {
    Points u(x.rows(), 3);
    for (Eigen::Index i = 0; i < x.rows(); ++i) u.row(i) << 0.1 * x(i, 1), -0.2 * x(i, 0), 0.05 * x(i, 2) + 1e-3;
    return u;
  };
  const DisplacementErrors e = compareDisplacements(coarse, field(coarse.nodes()), fine, field(fine.nodes()),
                                                    Points(), "chest_wall", "");
  EXPECT_LT(e.max_mm, 1e-9);
  EXPECT_GT(e.max_displacement_mm, 1.0);
  // Same box surface, same affine map: the deformed surfaces coincide.
  EXPECT_LT(e.surface_distance_max_mm, 1e-9);
  EXPECT_LT(e.rest_surface_distance_mean_mm, 1e-9);
  // Volume change of u = A x + c is det(I + A) − 1 on both meshes.
  EXPECT_NEAR(e.volume_change_percent, e.reference_volume_change_percent, 1e-9);
  EXPECT_NEAR(e.volume_change_percent, 100 * (1.05 * (1.0 + 0.1 * 0.2) - 1.0), 1e-9);  // det(I + A) = 1.071
}

TEST(ErrorMetrics, PointSurfaceDistanceMatchesBruteForce) {
  const TetMesh m = makeBoxMesh({5, 3, 4}, {0.05, 0.03, 0.04});
  const BoundarySurface& s = m.boundary();
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> d(-0.03, 0.08);
  Points p(300, 3);
  for (int i = 0; i < p.rows(); ++i) p.row(i) << d(rng), d(rng), d(rng);
  const Eigen::VectorXd fast = pointSurfaceDistance(p, m.nodes(), s.triangles);
  for (int i = 0; i < p.rows(); ++i) {
    double best = 1e300;
    for (int f = 0; f < s.triangles.rows(); ++f)
      best = std::min(best, (closestPointOnTriangle(p.row(i).transpose(), m.nodes().row(s.triangles(f, 0)).transpose(),
                                                    m.nodes().row(s.triangles(f, 1)).transpose(),
                                                    m.nodes().row(s.triangles(f, 2)).transpose()) -
                             p.row(i).transpose())
                                .norm());
    EXPECT_NEAR(fast[i], best, 1e-14) << "point " << i;
  }
  // No triangles: every point is infinitely far (not measured to the bare vertices).
  const Eigen::VectorXd none = pointSurfaceDistance(p, m.nodes(), Triangles(0, 3));
  ASSERT_EQ(none.size(), p.rows());
  EXPECT_TRUE(none.array().isInf().all());
}

TEST(ModelChoice, CoarsestPointWhoseFinerPointsAllMeetTheTarget) {
  std::vector<ErrorCurvePoint> curve = {
      {5000, 6012, 1.5, 0.1}, {10000, 10692, 2.5, 0.2}, {20000, 20132, 1.8, 0.4}, {48000, 47873, 1.2, 1.0}};
  ModelChoice c = chooseCoarsestModel(curve, 2.0);
  EXPECT_TRUE(c.met);
  EXPECT_EQ(c.target_elements, 20000);  // 5k meets it by chance, but 10k does not
  EXPECT_DOUBLE_EQ(c.expected_error_mm, 1.8);
  c = chooseCoarsestModel(curve, 3.0);
  EXPECT_EQ(c.target_elements, 5000);
  c = chooseCoarsestModel(curve, 1.0);
  EXPECT_FALSE(c.met);
  EXPECT_EQ(c.target_elements, 48000);
  EXPECT_NE(c.explanation.find("no measured model"), std::string::npos);
  EXPECT_THROW(chooseCoarsestModel({}, 1.0), std::invalid_argument);
  EXPECT_THROW(chooseCoarsestModel(curve, -1.0), std::invalid_argument);
  EXPECT_EQ(errorMeasureName(errorMeasureFromName("lesion")), "lesion");
  EXPECT_THROW(errorMeasureFromName("median"), std::invalid_argument);
}
