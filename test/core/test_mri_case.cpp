// The `mri:` case (mri/mri_case.h, model/model_case.h): its map and errors, the effective case that
// repeats it, a synthetic T1 MRI of the VICTRE phantom as a model case (segmentation, scores, nipple,
// lesions from points and from a label image, the supine MRI of a zero displacement), one breast of
// two, the bad inputs with messages naming the files, and breast_sim_run's outputs on a small case.
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

#include <nlohmann/json.hpp>

#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/mri/mri_case.h"
#include "breast_sim/core/mri/synthetic_mri.h"
#include "breast_sim/core/pipeline/case_file.h"
#include "mri_test_images.h"
#include "temp_dir.h"

namespace fs = std::filesystem;
using namespace breast_sim::core;
using breast_sim::test::messageOf;
using breast_sim::test::smallImageParams;
using breast_sim::test::TempDir;
using breast_sim::test::victreLps;

namespace {

const fs::path kSource = fs::path(BREAST_SIM_TEST_DATA_DIR) / ".." / "..";

/// One synthetic T1 MRI of the VICTRE phantom (seed 7, not the seed the defaults were set on) and its
/// truth, written once for every test of this file.
struct SharedMri {
  TempDir dir{"breast_sim_mri_case"};
  SyntheticMri mri;
  std::string image, truth;
  SharedMri() {
    mri = renderSyntheticT1(victreLps(), TissueLabels{}, smallImageParams(7));
    image = dir.path("prone_t1.nii.gz");
    truth = dir.path("truth.nrrd");
    writeMriVolume(image, mri.image);
    writeLabelImage(truth, mri.truth);
  }
};
const SharedMri& shared() {
  static const SharedMri s;
  return s;
}

/// Points of the phantom inside the breast [m] (LPS; the breast hangs towards -y).
const Eigen::Vector3d kLesion(-10e-3, -40e-3, -10e-3);
const Eigen::Vector3d kBlobA(15e-3, -30e-3, 10e-3);
const Eigen::Vector3d kBlobB(-5e-3, -55e-3, -20e-3);

std::string readText(const fs::path& p) {
  std::ifstream in(p);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

/// A label image on the MRI's grid with a ball of `value` at each centre.
LabelImage balls(const ImageGeometry& g, const std::vector<std::pair<Eigen::Vector3d, double>>& centres_radii,
                 std::uint16_t value) {
  LabelImage l = labelImageLike(ScalarImage{g, std::vector<float>(static_cast<std::size_t>(g.numVoxels()), 0.0f)});
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i)
        for (const auto& [c, r] : centres_radii)
          if ((g.indexToPhysical(Eigen::Vector3d(i, j, k)) - c).norm() <= r) l.at(i, j, k) = value;
  return l;
}

}  // namespace

TEST(MriCase, TheMapIsReadWithItsDefaultsAndPathsAgainstTheCaseFolder) {
  TempDir dir("breast_sim_mri_case");
  fs::create_directories(dir.path("cases"));
  const std::string file = dir.write("cases/a.yaml", "mri: {path: ../scans/t1.nii.gz}\n");
  const MriCaseSource s = loadMriCaseSource(file);
  EXPECT_EQ(s.path, (fs::path(dir.path("scans")) / "t1.nii.gz").lexically_normal().string());
  EXPECT_EQ(s.series_uid, "");
  EXPECT_EQ(s.breasts, MriCaseSource::Breasts::kBoth);
  EXPECT_TRUE(std::isnan(s.midline_x_m));
  EXPECT_EQ(s.lesion_labels, "");
  EXPECT_EQ(s.truth, "");
  const MriCaseSource t = loadMriCaseSource(dir.write(
      "cases/b.yaml", "mri: {path: /data/dicom, series_uid: 1.2.3, breasts: right, midline_x_mm: -12.5, "
                      "lesion_labels: l.nrrd, truth: t.nrrd}\n"));
  EXPECT_EQ(t.path, "/data/dicom");
  EXPECT_EQ(t.series_uid, "1.2.3");
  EXPECT_EQ(t.breasts, MriCaseSource::Breasts::kRight);
  EXPECT_DOUBLE_EQ(t.midline_x_m, -12.5e-3);
  EXPECT_EQ(t.lesion_labels, dir.path("cases/l.nrrd"));
  EXPECT_EQ(t.truth, dir.path("cases/t.nrrd"));
  EXPECT_TRUE(std::isnan(loadMriCaseSource(dir.write("cases/c.yaml", "mri: {path: x.nii, midline_x_mm: auto}\n")).midline_x_m));
}

TEST(MriCase, EveryBadKeyIsAnErrorNamingItAndTheFix) {
  TempDir dir("breast_sim_mri_case");
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"mri: {series_uid: 1.2}\n", "'mri.path': missing: give the prone MRI"},
      {"mri: {path: ''}\n", "'mri.path': empty"},
      {"mri: {path: [a, b]}\n", "'mri.path': expected a text value"},
      {"mri: {path: x.nii, breast: left}\n", "'mri.breast': unknown key; the keys of 'mri' are: breasts, lesion_labels"},
      {"mri: {path: x.nii, breasts: middle}\n", "'mri.breasts': expected one of both, left, right, got 'middle'"},
      {"mri: {path: x.nii, midline_x_mm: abc}\n", "'mri.midline_x_mm': expected a number"},
      {"mri: [x.nii]\n", "'mri': expected a map"},
      {"mri: {path: x.nii}\nimage: {path: y.nrrd}\n", "give exactly one of"},
      {"mri: {path: x.nii}\nsegmentation: {body_threshold: 2}\n", "'segmentation.body_threshold': expected a value in (0, 1)"},
  };
  for (const auto& [text, expected] : cases) {
    SCOPED_TRACE(text);
    const std::string file = dir.write("case.yaml", text);
    const std::string message = messageOf([&] { effectiveCaseYaml(file); });
    EXPECT_NE(message.find(file), std::string::npos) << message;
    EXPECT_NE(message.find(expected), std::string::npos) << message;
  }
}

// The model layer does not segment: loadModelCase alone refuses an MRI case, naming the file, and
// reads no image.
TEST(MriCase, TheModelLayerAloneRefusesAnMriCase) {
  TempDir dir("breast_sim_mri_case");
  const std::string file = dir.write("case.yaml", "mri: {path: missing.nii.gz}\n");
  const std::string message = messageOf([&] { loadModelCase(file); });
  EXPECT_EQ(message.rfind(file + ": 'mri': a prone MRI case is segmented before it is meshed", 0), 0u) << message;
  EXPECT_EQ(message.find("missing.nii.gz"), std::string::npos) << message;
}

// case_effective.yaml repeats an MRI case: every key of `mri:` and `segmentation:` is written, and
// each changed on its own is read back as written and changes nothing else.
TEST(MriCase, TheEffectiveCaseRepeatsItKeyByKey) {
  TempDir dir("breast_sim_mri_case");
  const std::string first = effectiveCaseYaml(dir.write("case.yaml", "mri: {path: t1.nii.gz}\n"));
  const YAML::Node base = YAML::Load(first);
  EXPECT_EQ(base["mri"]["path"].as<std::string>(), dir.path("t1.nii.gz"));
  EXPECT_EQ(base["mri"]["breasts"].as<std::string>(), "both");
  EXPECT_EQ(base["mri"]["midline_x_mm"].as<std::string>(), "auto");
  EXPECT_EQ(base["segmentation"].size(), 17u);
  EXPECT_EQ(effectiveCaseYaml(dir.write("again.yaml", first)), first);

  const std::vector<std::tuple<std::string, std::string, std::string>> changes = {
      {"mri", "path", "/elsewhere/t1.nrrd"},
      {"mri", "series_uid", "1.2.840.99"},
      {"mri", "breasts", "left"},
      {"mri", "midline_x_mm", "-7.25"},
      {"mri", "lesion_labels", "/data/lesions.nrrd"},
      {"mri", "truth", "/data/truth.nrrd"},
      {"segmentation", "prone_gravity_direction", "[0, 0, -1]"},
      {"segmentation", "bias_correction", "false"},
      {"segmentation", "n4_shrink_factor", "2"},
      {"segmentation", "n4_fitting_levels", "4"},
      {"segmentation", "n4_iterations", "20"},
      {"segmentation", "n4_spline_distance_mm", "80"},
      {"segmentation", "smoothing_sigma_mm", "0"},
      {"segmentation", "body_threshold", "0.25"},
      {"segmentation", "body_noise_margin", "4"},
      {"segmentation", "min_fat_component_share", "0.2"},
      {"segmentation", "chest_wall_min_thickness_mm", "6"},
      {"segmentation", "boundary_median_window_mm", "20"},
      {"segmentation", "boundary_smoothing_mm", "4"},
      {"segmentation", "boundary_outlier_mm", "2.5"},
      {"segmentation", "min_boundary_coverage", "0.6"},
      {"segmentation", "min_component_share", "0.1"},
      {"segmentation", "skin_thickness_mm", "1.5"},
  };
  std::size_t keys = 0;
  for (const char* section : {"mri", "segmentation"}) keys += base[section].size();
  EXPECT_EQ(changes.size(), keys) << "a key of the effective case is not changed by this test";
  const auto emit = [](const YAML::Node& n) {
    YAML::Emitter e;
    e << n;
    return std::string(e.c_str());
  };
  for (const auto& [section, key, value] : changes) {
    SCOPED_TRACE(section + "." + key + " = " + value);
    ASSERT_TRUE(base[section][key]) << "not in the effective case";
    YAML::Node changed = YAML::Clone(base);
    changed[section][key] = YAML::Load(value);
    const YAML::Node back = YAML::Load(effectiveCaseYaml(dir.write("changed.yaml", emit(changed))));
    for (const char* s2 : {"mri", "segmentation"})
      for (const auto& kv : base[s2]) {
        const std::string k2 = kv.first.as<std::string>();
        const YAML::Node want = (s2 == section && k2 == key) ? changed[s2][k2] : base[s2][k2];
        EXPECT_EQ(emit(back[s2][k2]), emit(want)) << s2 << "." << k2;
      }
  }
}

// docs/case_files.md shows the `mri:` and `segmentation:` maps with every key at its default.
TEST(MriCase, TheDocumentedMapsListEveryKeyWithTheCodesDefault) {
  const std::string doc = readText(kSource / "docs" / "case_files.md");
  const std::size_t section = doc.find("## A prone MRI instead of a label image");
  ASSERT_NE(section, std::string::npos) << "docs/case_files.md has no section on MRI cases";
  const std::size_t open = doc.find("```yaml\n", section);
  ASSERT_NE(open, std::string::npos);
  const std::size_t close = doc.find("```", open + 8);
  const std::string block = doc.substr(open + 8, close - open - 8);
  TempDir dir("breast_sim_mri_case");
  const YAML::Node documented = YAML::Load(effectiveCaseYaml(dir.write("documented.yaml", block)));
  YAML::Node block_yaml = YAML::Load(block);
  const std::string path = block_yaml["mri"]["path"].as<std::string>();
  const YAML::Node defaults = YAML::Load(effectiveCaseYaml(dir.write("defaults.yaml", "mri: {path: " + path + "}\n")));
  for (const char* s : {"mri", "segmentation"})
    for (const auto& kv : defaults[s]) {
      const std::string k = kv.first.as<std::string>();
      EXPECT_TRUE(block_yaml[s][k]) << s << "." << k << " is not documented";
      EXPECT_EQ(YAML::Dump(documented[s][k]), YAML::Dump(kv.second)) << s << "." << k;
    }
}

// The synthetic VICTRE MRI as a case: segmented, scored against its truth, the nipple found, the
// listed lesion painted, the lesion label image's two balls become two lesions, the model built;
// a zero displacement gives the prone voxels back.
TEST(MriCase, ASyntheticVictreMriBecomesAModelWithItsLesions) {
  const SharedMri& m = shared();
  for (const Eigen::Vector3d& p : {kLesion, kBlobA, kBlobB})
    ASSERT_TRUE(TissueLabels{}.isTissue(m.mri.truth.labelAt(p))) << p.transpose() * 1e3 << " mm is not in the breast";
  writeLabelImage(m.dir.path("lesions.nrrd"), balls(m.mri.image.geometry, {{kBlobA, 4e-3}, {kBlobB, 3e-3}}, 3));
  std::vector<std::string> stages;
  const std::string file = m.dir.write("case.yaml", "mri: {path: prone_t1.nii.gz, truth: truth.nrrd, lesion_labels: lesions.nrrd}\n"
                                                    "lesions:\n  - {name: L1, position_mm: [-10, -40, -10], radius_mm: 5}\n"
                                                    "meshing: {target_elements: 2000}\n");
  const ModelCase c = loadModelCaseWithMri(file, [&](const std::string& s) { stages.push_back(s); });
  EXPECT_EQ(stages, (std::vector<std::string>{"reading", "segmentation"}));
  ASSERT_TRUE(c.mri);
  const MriCase& mri = *c.mri;
  EXPECT_EQ(mri.volume.info.format, "NIfTI");
  EXPECT_EQ(c.image.labels, mri.segmentation.labels.labels);  // both breasts: the segmentation as it is
  EXPECT_TRUE(c.image.size == m.mri.image.geometry.size);
  EXPECT_TRUE(c.prone_gravity_direction.isApprox(Eigen::Vector3d(0, -1, 0)));
  ASSERT_TRUE(mri.scores);
  EXPECT_GE(mri.scores->score("breast").dice, 0.95);
  EXPECT_LE(mri.scores->boundary.mean_mm, 1.5);
  EXPECT_LE(mri.scores->boundary.p95_mm, 3.0);
  ASSERT_EQ(c.nipples_m.size(), 1u);
  EXPECT_LE((c.nipples_m[0] - Eigen::Vector3d(0.1e-3, -82.2e-3, -25.3e-3)).norm(), 3e-3) << c.nipples_m[0].transpose() * 1e3;
  // The listed lesion first, then the label image's pieces, largest first.
  ASSERT_EQ(c.lesions.size(), 3u);
  EXPECT_EQ(c.lesions[0].name, "L1");
  EXPECT_EQ(c.image.labelAt(kLesion), segmentationLabel(TissueClass::kLesion));
  EXPECT_EQ(c.lesions[1].name, "label_3_1");
  EXPECT_EQ(c.lesions[2].name, "label_3_2");
  EXPECT_LE((c.lesions[1].position_m - kBlobA).norm(), 0.3e-3);
  EXPECT_LE((c.lesions[2].position_m - kBlobB).norm(), 0.3e-3);
  EXPECT_NEAR(c.lesions[1].radius_m, 4e-3, 0.3e-3);
  EXPECT_NEAR(c.lesions[2].radius_m, 3e-3, 0.3e-3);

  const SimulationModel model = buildSimulationModel(c);
  EXPECT_GT(model.mesh.numTets(), 1000);
  EXPECT_EQ(model.lesion_embedding.points().size(), 3u);
  EXPECT_EQ(model.mesh.nodeSet(node_sets::kNipple).size(), 1u);
  EXPECT_FALSE(model.mesh.nodeSet(node_sets::kChestWall).empty());

  // No displacement: the supine grid lies on the prone lattice and every body voxel is the prone voxel.
  const SupineImages same = simulatedSupineMri(mri, model.mesh, Points::Zero(model.mesh.numNodes(), 3));
  const ImageGeometry& g = same.image.geometry;
  const ImageGeometry& prone = mri.volume.image.geometry;
  long body = 0, equal = 0;
  for (int k = 0; k < g.size.z(); ++k)
    for (int j = 0; j < g.size.y(); ++j)
      for (int i = 0; i < g.size.x(); ++i) {
        const long v = g.index(i, j, k);
        if (!TissueLabels{}.isTissue(same.labels.labels[v])) continue;
        ++body;
        const Eigen::Vector3d q = prone.physicalToIndex(g.indexToPhysical(Eigen::Vector3d(i, j, k)));
        const Eigen::Vector3i r = q.array().round().cast<int>();
        ASSERT_LE((q - r.cast<double>()).cwiseAbs().maxCoeff(), 1e-6);
        equal += same.image.values[v] == mri.volume.image.values[prone.index(r.x(), r.y(), r.z())];
      }
  EXPECT_GT(body, 100000);
  EXPECT_EQ(equal, body);
}

// A two-breast image (the VICTRE MRI beside its mirror image): `breasts: left` simulates the breast on
// the patient's left (+x) of the midline midway between the two nipples and holds the other as chest
// wall; `right` the other one; a lesion in the breast not simulated is an error naming it.
TEST(MriCase, OneBreastOfTwoIsSimulatedAndTheOtherHeld) {
  const SharedMri& m = shared();
  const ScalarImage& one = m.mri.image;
  const int nx = one.geometry.size.x();
  ScalarImage two;
  two.geometry = one.geometry;
  two.geometry.size.x() = 2 * nx;
  two.geometry.origin_m.x() -= nx * one.geometry.spacing_m.x();
  two.values.resize(static_cast<std::size_t>(two.geometry.numVoxels()));
  for (int k = 0; k < one.geometry.size.z(); ++k)
    for (int j = 0; j < one.geometry.size.y(); ++j)
      for (int i = 0; i < nx; ++i) {
        const float v = one.values[one.geometry.index(i, j, k)];
        two.values[two.geometry.index(nx + i, j, k)] = v;      // the phantom where it was
        two.values[two.geometry.index(nx - 1 - i, j, k)] = v;  // its mirror image across x = x_m
      }
  const double x_mirror = one.geometry.origin_m.x() - 0.5 * one.geometry.spacing_m.x();
  TempDir dir("breast_sim_mri_case");
  writeMriVolume(dir.path("two.nii.gz"), two);
  const TissueLabels map;
  for (const char* side : {"left", "right"}) {
    SCOPED_TRACE(side);
    const ModelCase c = loadModelCaseWithMri(dir.write("case.yaml", std::string("mri: {path: two.nii.gz, breasts: ") + side + "}\n"));
    const MriCase& mri = *c.mri;
    ASSERT_EQ(mri.segmentation.report.nipples_m.size(), 2u);
    EXPECT_NEAR(mri.midline_x_m, x_mirror, 1e-3);
    const double sign = std::string(side) == "left" ? 1.0 : -1.0;
    ASSERT_EQ(c.nipples_m.size(), 1u);
    EXPECT_GT(sign * (c.nipples_m[0].x() - x_mirror), 20e-3);
    long kept = 0, held = 0;
    for (int k = 0; k < c.image.size.z(); ++k)
      for (int j = 0; j < c.image.size.y(); ++j)
        for (int i = 0; i < c.image.size.x(); ++i) {
          const bool tissue_before = map.isTissue(mri.segmentation.labels.at(i, j, k));
          const bool tissue_now = map.isTissue(c.image.at(i, j, k));
          const bool on_side = sign * (c.image.indexToPhysical(Eigen::Vector3d(i, j, k)).x() - x_mirror) > 0;
          ASSERT_EQ(tissue_now, tissue_before && on_side) << i << ", " << j << ", " << k;
          if (tissue_before && !on_side) {
            ++held;
            EXPECT_EQ(map.classify(c.image.at(i, j, k)), TissueClass::kChestWall);
          }
          kept += tissue_now;
        }
    EXPECT_GT(kept, 100000);
    EXPECT_GT(held, kept / 2);
  }
  // The lesion point of the mirrored breast, with the left breast simulated.
  const std::string file = dir.write("case.yaml", "mri: {path: two.nii.gz, breasts: left}\n"
                                                  "lesions: [{name: R1, position_mm: [" +
                                                      std::to_string(1e3 * (2 * x_mirror - kLesion.x())) + ", -40, -10]}]\n");
  const std::string message = messageOf([&] { loadModelCaseWithMri(file); });
  EXPECT_NE(message.find(file + ": 'lesions': lesion R1 at x = "), std::string::npos) << message;
  EXPECT_NE(message.find("lies in the breast the case does not simulate (mri.breasts: left"), std::string::npos) << message;
}

// Bad input: each error names the case file, the MRI and what to fix; nothing is half-built.
TEST(MriCase, BadInputsAreClearErrorsNamingTheFiles) {
  TempDir dir("breast_sim_mri_case");
  // Not an image.
  std::ofstream(dir.path("notes.nii")) << "not an image\n";
  // A 2-D image: one slice.
  ScalarImage slice;
  slice.geometry.size = Eigen::Vector3i(8, 8, 1);
  slice.values.assign(64, 100.0f);
  writeMriVolume(dir.path("slice.nii.gz"), slice);
  // A DICOM series with a missing slice.
  ScalarImage small;
  small.geometry.size = Eigen::Vector3i(9, 7, 6);
  small.values.assign(9 * 7 * 6, 500.0f);
  writeDicomSeries(dir.path("series"), small);
  fs::remove(dir.path("series/IM00004.dcm"));
  // An image with no breast in it: Rician noise only.
  ScalarImage noise;
  noise.geometry.size = Eigen::Vector3i(40, 40, 40);
  noise.values.resize(64000);
  std::uint32_t state = 12345;
  const auto gauss = [&] {  // Box-Muller on a small LCG: reproducible noise
    state = state * 1664525u + 1013904223u;
    const double u1 = (state >> 8) * (1.0 / 16777216.0) + 1e-9;
    state = state * 1664525u + 1013904223u;
    const double u2 = (state >> 8) * (1.0 / 16777216.0);
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2 * M_PI * u2);
  };
  for (float& v : noise.values) v = static_cast<float>(20.0 * std::hypot(gauss(), gauss()));
  writeMriVolume(dir.path("noise.nii.gz"), noise);
  const SharedMri& m = shared();

  const std::vector<std::tuple<std::string, std::string, std::string>> cases = {
      {"mri: {path: " + dir.path("notes.nii") + "}\n", dir.path("notes.nii"), "not an image of a supported format"},
      {"mri: {path: " + dir.path("slice.nii.gz") + "}\n", dir.path("slice.nii.gz"), "the MRI must be a 3-D volume"},
      {"mri: {path: " + dir.path("series") + "}\n", "IM00005.dcm", "a slice is missing or the series mixes acquisitions"},
      {"mri: {path: " + dir.path("noise.nii.gz") + "}\n", dir.path("noise.nii.gz"), "breast MRI"},
      {"mri: {path: " + m.image + "}\nlesions: [{name: L9, position_mm: [40, -80, 45]}]\n", m.image,
       "lesion L9 at (40.0, -80.0, 45.0) mm lies in the air, not in the breast; check its position"},
      {"mri: {path: " + m.image + ", truth: " + dir.path("slice.nii.gz") + "}\n", dir.path("slice.nii.gz"),
       "the truth must be a label image on the MRI's grid"},
      {"mri: {path: " + dir.path("missing.nii.gz") + "}\n", dir.path("missing.nii.gz"), "no such file or folder"},
  };
  for (const auto& [text, names, fix] : cases) {
    SCOPED_TRACE(text);
    const std::string file = dir.write("case.yaml", text);
    const std::string message = messageOf([&] { loadModelCaseWithMri(file); });
    EXPECT_EQ(message.rfind(file + ": 'mri", 0), 0u) << message;
    EXPECT_NE(message.find(names), std::string::npos) << message;
    EXPECT_NE(message.find(fix), std::string::npos) << message;
  }
}

// breast_sim_run on a small MRI case (2,000 elements): the segmentation's outputs and summary, the
// simulated supine MRI in NIfTI and NRRD (the same voxels, the resampling of the written deformed
// model), the lesion carried into the supine labels, and a case_effective.yaml that repeats the case.
TEST(MriCase, BreastSimRunWritesTheSegmentationAndTheSupineMri) {
  const SharedMri& m = shared();
  const std::string file = m.dir.write("run_case.yaml", "mri: {path: prone_t1.nii.gz, truth: truth.nrrd}\n"
                                                        "lesions:\n  - {name: L1, position_mm: [-10, -40, -10], radius_mm: 5}\n"
                                                        "meshing: {target_elements: 2000}\n");
  const fs::path out = m.dir.path("run");
  const std::string command = std::string(BREAST_SIM_TOOL_DIR) + "/breast_sim_run --case " + file + " --out " + out.string() +
                              " --quiet --frames 0 > " + m.dir.path("run.txt") + " 2>&1";
  const int status = std::system(command.c_str());
  const std::string printed = readText(m.dir.path("run.txt"));
  ASSERT_TRUE(WIFEXITED(status)) << printed;
  ASSERT_EQ(WEXITSTATUS(status), 0) << printed;
  for (const char* f : {"model.vtu", "supine.vtu", "prone_labels.nrrd", "segmentation.png", "segmentation.json",
                        "supine_mri.nii.gz", "supine_mri.nrrd", "supine_labels.nrrd", "supine_mri.png", "lesions.json",
                        "metrics.json", "case_effective.yaml"})
    EXPECT_TRUE(fs::exists(out / f)) << f;
  EXPECT_NE(printed.find("segmentation vs truth"), std::string::npos) << printed;
  EXPECT_NE(printed.find("Dice breast 0.9"), std::string::npos) << printed;
  EXPECT_NE(printed.find("chest-wall boundary mean"), std::string::npos) << printed;
  EXPECT_NE(printed.find("simulated supine MRI"), std::string::npos) << printed;

  const nlohmann::json seg = nlohmann::json::parse(readText(out / "segmentation.json"));
  EXPECT_GE(seg["truth"]["dice"]["breast"].get<double>(), 0.95);
  EXPECT_EQ(seg["breasts"], "both");
  const nlohmann::json metrics = nlohmann::json::parse(readText(out / "metrics.json"));
  EXPECT_TRUE(metrics["completed"].get<bool>());
  EXPECT_GT(metrics["supine_mri"]["body_voxels"].get<long>(), 100000);

  // NIfTI and NRRD hold the same image; it is the resampling of the written supine model.
  const MriVolume nii = readMriVolume((out / "supine_mri.nii.gz").string());
  const MriVolume nrrd = readMriVolume((out / "supine_mri.nrrd").string());
  ASSERT_TRUE(nii.image.geometry.size == nrrd.image.geometry.size);
  EXPECT_LE((nii.image.geometry.origin_m - nrrd.image.geometry.origin_m).norm(), 1e-6);
  EXPECT_EQ(nii.image.values, nrrd.image.values);
  MeshFields fields;
  const TetMesh deformed = readVtkUnstructured((out / "supine.vtu").string(), 1.0, &fields);
  const MeshField* u_mm = nullptr;
  for (const MeshField& f : fields.point_data)
    if (f.name == "displacement_mm") u_mm = &f;
  ASSERT_TRUE(u_mm);
  const Points u = u_mm->values * 1e-3;
  const TetMesh rest(deformed.nodes() - u, deformed.tets(), deformed.regionLabels());
  const MriVolume prone = readMriVolume(m.image);
  const LabelImage prone_labels = readLabelImage((out / "prone_labels.nrrd").string());
  const SupineImages again = resampleToSupine(rest, u, &prone.image, &prone_labels, nrrd.image.geometry);
  long differ = 0;
  for (std::size_t v = 0; v < again.image.values.size(); ++v) differ += std::abs(again.image.values[v] - nrrd.image.values[v]) > 1e-2f;
  EXPECT_LE(differ, static_cast<long>(again.image.values.size() / 1000)) << differ << " voxels differ";

  // The lesion's final position lies in the lesion label carried along. An MRI case has no supine
  // target surface, so the final state is gravity with sliding.
  const nlohmann::json lesions = nlohmann::json::parse(readText(out / "lesions.json"));
  ASSERT_EQ(lesions.size(), 1u);
  ASSERT_TRUE(lesions[0].contains("gravity_mm")) << lesions.dump();
  EXPECT_FALSE(lesions[0].contains("supine_mm")) << lesions.dump();
  const nlohmann::json& final_mm = lesions[0]["gravity_mm"];
  const Eigen::Vector3d supine_lesion(final_mm[0].get<double>(), final_mm[1].get<double>(), final_mm[2].get<double>());
  EXPECT_GT(lesions[0]["gravity_moved_mm"].get<double>(), 3.0);
  EXPECT_EQ(readLabelImage((out / "supine_labels.nrrd").string()).labelAt(supine_lesion * 1e-3), segmentationLabel(TissueClass::kLesion));

  // case_effective.yaml repeats the case.
  const std::string effective = readText(out / "case_effective.yaml");
  EXPECT_NE(effective.find("path: " + m.image), std::string::npos);
  const std::string again_path = m.dir.write("effective_again.yaml", effective);
  EXPECT_EQ(effectiveCaseYaml(again_path), effectiveCaseYaml((out / "case_effective.yaml").string()));
}
