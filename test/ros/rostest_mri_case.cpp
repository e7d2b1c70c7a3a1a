// rostest client for mri_case.test: the node on the shipped MRI case (config/victre_mri_case.yaml),
// its MRI rendered here from the VICTRE phantom as scripts/run_mri_case.sh renders it (a DICOM series
// and its truth; a tighter field of view). The node starts without a case (its start-up case file
// does not exist, and it says so); ~load_case reads, segments and meshes the case with each stage on
// ~state; the precomputed lesion is published where the case puts it and moves; ~write_supine_mri
// writes the simulated supine MRI of the current state into the output folder (what the core makes of
// the published mesh) in each format, one file each, refuses names outside the folder (`..`, absolute
// paths, links leaving it), a missing subfolder and an existing file unless asked, leaving nothing
// behind, and replaces a file by a rename; bad input
// (a non-MRI file, a 2-D image, a series with a missing slice, an image with no breast, a lesion
// outside the breast) is refused with a message naming the file and the fix, the model kept.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include <sys/stat.h>

#include <ros/ros.h>

#include <breast_sim/LesionArray.h>
#include <breast_sim/LoadCase.h>
#include <breast_sim/NodeState.h>
#include <breast_sim/StartPrecomputation.h>
#include <breast_sim/TetrahedralMesh.h>
#include <breast_sim/WriteSupineMri.h>

#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/mri/mri_case.h"
#include "breast_sim/core/mri/synthetic_mri.h"
#include "breast_sim/ros_interface/conversions.h"
#include "node_state_folder.h"
#include "wait_until.h"

namespace fs = std::filesystem;

namespace {

std::mutex m;
breast_sim::NodeState::ConstPtr state;
std::vector<std::string> stages_seen;  ///< every stage ~state showed, in order, without repeats
breast_sim::LesionArray::ConstPtr lesions;
breast_sim::TetrahedralMesh::ConstPtr mesh;

void onState(const breast_sim::NodeState::ConstPtr& msg) {
  std::lock_guard<std::mutex> l(m);
  state = msg;
  if (stages_seen.empty() || stages_seen.back() != msg->stage) stages_seen.push_back(msg->stage);
}
void onLesions(const breast_sim::LesionArray::ConstPtr& msg) {
  std::lock_guard<std::mutex> l(m);
  lesions = msg;
}
void onMesh(const breast_sim::TetrahedralMesh::ConstPtr& msg) {
  std::lock_guard<std::mutex> l(m);
  mesh = msg;
}

template <class F>
bool waitUntil(F&& condition, double timeout_s) {
  return breast_sim::test_fixtures::waitUntil(m, std::forward<F>(condition), timeout_s);
}

std::string param(const std::string& name) {
  std::string v;
  ros::NodeHandle("~").getParam(name, v);
  return v;
}

breast_sim::WriteSupineMri::Response writeSupine(const std::string& name, bool replace) {
  breast_sim::WriteSupineMri call;
  call.request.file_name = name;
  call.request.replace = replace;
  EXPECT_TRUE(ros::service::call("/breast_sim/write_supine_mri", call));
  return call.response;
}

/// ~load_case, asked again while a job from before still ends (a busy node refuses).
breast_sim::LoadCase::Response load(const std::string& case_file, int target_elements) {
  breast_sim::LoadCase call;
  call.request.case_file = case_file;
  call.request.target_elements = target_elements;
  for (int attempt = 0; attempt < 300; ++attempt) {
    EXPECT_TRUE(ros::service::call("/breast_sim/load_case", call));
    if (call.response.message.find("busy") == std::string::npos) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  return call.response;
}

ino_t inode(const std::string& path) {
  struct stat st {};
  return ::lstat(path.c_str(), &st) == 0 ? st.st_ino : 0;
}

/// Every entry under `folder` (links not followed) with its inode, size and modification time: two
/// listings are equal when nothing was created, removed or written.
std::map<std::string, std::tuple<ino_t, off_t, long>> listing(const fs::path& folder) {
  std::map<std::string, std::tuple<ino_t, off_t, long>> entries;
  for (const auto& entry : fs::recursive_directory_iterator(folder)) {
    struct stat st {};
    if (::lstat(entry.path().c_str(), &st) == 0)
      entries[entry.path().string()] = {st.st_ino, st.st_size, st.st_mtim.tv_sec * 1000000000L + st.st_mtim.tv_nsec};
  }
  return entries;
}

std::string fileText(const fs::path& path) {
  std::ifstream in(path);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

}  // namespace

namespace {

/// The shipped case on an MRI rendered here: `base:` the shipped case, its `mri:` paths replaced.
std::string renderedCase() {
  static const std::string file = [] {
    using namespace breast_sim::core;
    const std::string dir = param("output_folder") + "/victre_t1";
    fs::remove_all(dir);
    fs::create_directories(dir);
    SyntheticMriParams p;  // the generator's defaults but a field of view 5 mm around the tissue, 25 mm of thorax
    p.margin_mm = 5.0;
    p.thorax_depth_mm = 25.0;
    const SyntheticMri mri = renderSyntheticT1(victrePhantomInLps(readLabelImage(param("victre_labels"))), TissueLabels{}, p);
    writeDicomSeries(dir + "/dicom", mri.image);
    writeLabelImage(dir + "/truth.nrrd", mri.truth);
    const std::string case_file = dir + "/victre_mri_case.yaml";
    std::ofstream(case_file) << "base: " << param("case_file") << "\nmri: {path: dicom, truth: truth.nrrd}\n";
    return case_file;
  }();
  return file;
}

}  // namespace

TEST(MriCase, WithoutItsStartUpCaseTheNodeSaysWhichFileIsMissing) {
  ASSERT_TRUE(waitUntil([] { return state && state->state == breast_sim::NodeState::IDLE; }, 60.0));
  std::lock_guard<std::mutex> l(m);
  EXPECT_FALSE(state->model_loaded);
  EXPECT_NE(state->message.find("'" + param("start_up_case_file") + "' does not exist"), std::string::npos) << state->message;
  EXPECT_NE(state->message.find("no model loaded"), std::string::npos) << state->message;
}

TEST(MriCase, TheNodeSegmentsMeshesAndPrecomputesTheMriCase) {
  {
    std::lock_guard<std::mutex> l(m);
    stages_seen.clear();
  }
  const breast_sim::LoadCase::Response r = load(renderedCase(), 3000);
  ASSERT_TRUE(r.success) << r.message;
  EXPECT_NE(r.message.find("segmented in"), std::string::npos) << r.message;
  EXPECT_NE(r.message.find("against the truth: breast Dice 0.9"), std::string::npos) << r.message;
  ASSERT_TRUE(waitUntil([] { return state->state == breast_sim::NodeState::IDLE && state->model_loaded; }, 30.0));
  {
    std::lock_guard<std::mutex> l(m);
    std::vector<std::string> loading;
    for (const std::string& stage : stages_seen)
      if (stage == "reading" || stage == "segmentation" || stage == "meshing" || stage == "setup") loading.push_back(stage);
    EXPECT_EQ(loading, (std::vector<std::string>{"reading", "segmentation", "meshing", "setup"}));
    EXPECT_EQ(state->stage, "idle");
    EXPECT_FALSE(state->precomputed);
  }
  // Before the precomputation the supine MRI shows the rest shape.
  const breast_sim::WriteSupineMri::Response rest = writeSupine("rest.nii.gz", true);
  EXPECT_TRUE(rest.success) << rest.message;
  EXPECT_NE(rest.message.find("the prone rest shape (not precomputed)"), std::string::npos) << rest.message;

  breast_sim::StartPrecomputation start;
  ASSERT_TRUE(ros::service::call("/breast_sim/start_precomputation", start));
  ASSERT_TRUE(start.response.accepted) << start.response.message;
  ASSERT_TRUE(waitUntil([] { return state->precomputed && state->state == breast_sim::NodeState::IDLE; }, 200.0))
      << state->state_name + ": " + state->message;
  ASSERT_TRUE(waitUntil([] { return lesions && lesions->valid && !lesions->lesions.empty(); }, 20.0));
  std::lock_guard<std::mutex> l(m);
  EXPECT_EQ(state->case_name, "victre_mri_case");
  ASSERT_EQ(lesions->lesions.size(), 1u);
  const breast_sim::Lesion& got = lesions->lesions[0];
  EXPECT_EQ(got.id, "L1");
  // Where the case puts it (LPS, the MRI's patient space), moved by the supine load.
  EXPECT_NEAR(got.prone_position.x, -0.010, 1e-9);
  EXPECT_NEAR(got.prone_position.y, -0.040, 1e-9);
  EXPECT_NEAR(got.prone_position.z, -0.010, 1e-9);
  const double moved = std::hypot(got.position.x - got.prone_position.x, got.position.y - got.prone_position.y,
                                  got.position.z - got.prone_position.z);
  EXPECT_GT(moved, 5e-3) << "the lesion moved " << moved * 1e3 << " mm";
}

// The supine MRI of the precomputed state: written where asked, the core's resampling of the published
// mesh; an existing file replaced only when asked, by a rename; each format one file.
TEST(MriCase, WritesTheSupineMriOfTheCurrentStateOnRequest) {
  ASSERT_TRUE(waitUntil([] { return state && state->precomputed && state->state == breast_sim::NodeState::IDLE && mesh; }, 200.0));
  const std::string folder = param("output_folder");
  ASSERT_FALSE(folder.empty());
  const std::string real = fs::canonical(folder).string();  // the answers name real paths
  fs::remove_all(folder + "/run1");
  fs::create_directories(folder + "/run1");  // the node makes no subfolder
  const breast_sim::WriteSupineMri::Response first = writeSupine("run1/supine_t1.nii.gz", false);
  ASSERT_TRUE(first.success) << first.message;
  EXPECT_EQ(first.path, real + "/run1/supine_t1.nii.gz");
  EXPECT_NE(first.message.find("the precomputed supine state"), std::string::npos) << first.message;
  ASSERT_TRUE(fs::exists(first.path));
  for (const auto& entry : fs::directory_iterator(folder + "/run1"))  // no temporary left behind
    EXPECT_EQ(entry.path().filename(), "supine_t1.nii.gz");

  // The core's supine MRI of the published state is what was written.
  breast_sim::TetrahedralMesh published;
  {
    std::lock_guard<std::mutex> l(m);
    published = *mesh;
  }
  using namespace breast_sim;
  const core::MriCase mri = core::loadMriCase(renderedCase());
  const core::SupineImages expected = core::simulatedSupineMri(mri, ros_interface::meshFromMessage(published),
                                                               ros_interface::displacementFromMessage(published));
  const core::MriVolume written = core::readMriVolume(first.path);
  EXPECT_EQ(written.info.format, "NIfTI");
  ASSERT_TRUE(written.image.geometry.size == expected.image.geometry.size);
  EXPECT_LE((written.image.geometry.origin_m - expected.image.geometry.origin_m).norm(), 1e-6);
  long differ = 0;
  for (std::size_t v = 0; v < expected.image.values.size(); ++v)
    differ += std::abs(written.image.values[v] - expected.image.values[v]) > 1e-3f * (1.0f + std::abs(expected.image.values[v]));
  EXPECT_LE(differ, static_cast<long>(expected.image.values.size() / 1000)) << differ << " voxels differ";
  EXPECT_GT(expected.body_voxels, 100000);

  // An existing file: refused without replace (untouched), replaced with it by a rename (a new inode).
  const ino_t first_inode = inode(first.path);
  const breast_sim::WriteSupineMri::Response again = writeSupine("run1/supine_t1.nii.gz", false);
  EXPECT_FALSE(again.success);
  EXPECT_NE(again.message.find("exists; set replace to true to replace it"), std::string::npos) << again.message;
  EXPECT_EQ(inode(first.path), first_inode);
  const breast_sim::WriteSupineMri::Response replaced = writeSupine("run1/supine_t1.nii.gz", true);
  ASSERT_TRUE(replaced.success) << replaced.message;
  EXPECT_EQ(replaced.path, first.path);
  EXPECT_NE(inode(first.path), first_inode) << "the file was rewritten in place, not replaced by a rename";
  EXPECT_EQ(core::readMriVolume(first.path).image.values, written.image.values);
  for (const auto& entry : fs::directory_iterator(folder + "/run1"))
    EXPECT_EQ(entry.path().filename(), "supine_t1.nii.gz");

  // Every format from its extension, each a single file with the same voxels; an absolute name inside
  // the folder is taken as it is.
  fs::remove_all(folder + "/formats");
  fs::create_directories(folder + "/formats");
  const std::vector<std::pair<std::string, std::string>> formats = {
      {"formats/supine_t1.nii", "NIfTI"}, {"formats/supine_t1.nrrd", "NRRD"}, {real + "/formats/supine_t1.mha", "MetaImage"}};
  for (const auto& [name, format] : formats) {
    const breast_sim::WriteSupineMri::Response r = writeSupine(name, false);
    ASSERT_TRUE(r.success) << name << ": " << r.message;
    const core::MriVolume back = core::readMriVolume(r.path);
    EXPECT_EQ(back.info.format, format) << r.path;
    EXPECT_TRUE(back.image.geometry.size == written.image.geometry.size) << r.path;
    EXPECT_LE((back.image.geometry.origin_m - written.image.geometry.origin_m).norm(), 1e-6) << r.path;  // NIfTI: float mm
    EXPECT_EQ(back.image.values, written.image.values) << r.path;
  }
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(folder + "/formats")) files.push_back(entry.path().filename().string());
  std::sort(files.begin(), files.end());
  EXPECT_EQ(files, (std::vector<std::string>{"supine_t1.mha", "supine_t1.nii", "supine_t1.nrrd"}));
}

// Names that would reach outside ~output_folder, a missing subfolder, an unknown extension: each
// refused with the reason, before any resampling, and nothing written, inside or out.
TEST(MriCase, TheSupineMriIsWrittenOnlyInsideTheOutputFolder) {
  ASSERT_TRUE(waitUntil([] { return state && state->precomputed && state->state == breast_sim::NodeState::IDLE; }, 200.0));
  const fs::path folder = param("output_folder");
  const fs::path outside = folder.parent_path() / "mri_case_test_outside";
  fs::remove_all(outside);
  fs::create_directories(outside);
  std::ofstream(outside / "victim.nii.gz") << "not to be overwritten";
  fs::remove(folder / "escape");
  fs::remove(folder / "link.nii.gz");
  fs::create_directory_symlink(outside, folder / "escape");
  fs::create_symlink(outside / "victim.nii.gz", folder / "link.nii.gz");
  fs::remove_all(folder / "missing");
  const auto inside_before = listing(folder);
  const auto outside_before = listing(outside);

  const std::string outside_name = outside.filename().string();
  for (const auto& [name, why] : std::vector<std::pair<std::string, std::string>>{
           {"../" + outside_name + "/up.nii.gz", "has a '..' component, which is not allowed"},
           {"run1/../inside_but_dotted.nii.gz", "has a '..' component, which is not allowed"},
           {(outside / "absolute.nii.gz").string(), "is outside ~output_folder"},
           {"escape/through_link.nii.gz", "a symbolic link leaves the folder"},
           {"link.nii.gz", "is a symbolic link; the node never writes through one"},
           {"missing/supine.nii.gz", "does not exist"},
           {"picture.png", "has no known extension; end it in one of .nii.gz, .nii, .nrrd, .mha"},
           {"supine.mhd", "has no known extension"},
           {"", "no file name given"}}) {
    for (const bool replace : {false, true}) {
      const breast_sim::WriteSupineMri::Response r = writeSupine(name, replace);
      EXPECT_FALSE(r.success) << name;
      EXPECT_TRUE(r.path.empty()) << name;
      EXPECT_NE(r.message.find(why), std::string::npos) << r.message;
    }
  }
  EXPECT_EQ(listing(folder), inside_before) << "a refused request created, removed or changed a file";
  EXPECT_EQ(listing(outside), outside_before);
  EXPECT_EQ(fileText(outside / "victim.nii.gz"), "not to be overwritten");
  EXPECT_FALSE(fs::exists(folder / "missing"));
  fs::remove(folder / "escape");
  fs::remove(folder / "link.nii.gz");
  fs::remove_all(outside);
}

// Bad input, each refused with the file and the fix named; the precomputed model stays.
TEST(MriCase, BadInputIsRefusedAndTheModelKept) {
  ASSERT_TRUE(waitUntil([] { return state && state->precomputed && state->state == breast_sim::NodeState::IDLE; }, 200.0));
  const std::string dir = param("output_folder") + "/bad_inputs";
  fs::create_directories(dir);
  using namespace breast_sim::core;
  std::ofstream(dir + "/notes.nii") << "not an image\n";
  ScalarImage slice;
  slice.geometry.size = Eigen::Vector3i(8, 8, 1);
  slice.values.assign(64, 100.0f);
  writeMriVolume(dir + "/slice.nii.gz", slice);
  ScalarImage small;
  small.geometry.size = Eigen::Vector3i(9, 7, 6);
  small.values.assign(9 * 7 * 6, 500.0f);
  fs::remove_all(dir + "/series");
  writeDicomSeries(dir + "/series", small);
  fs::remove(dir + "/series/IM00004.dcm");
  ScalarImage empty;  // no breast: an image of air with a faint, even signal
  empty.geometry.size = Eigen::Vector3i(40, 40, 40);
  empty.values.assign(64000, 0.0f);
  for (int v = 0; v < 64000; v += 7) empty.values[v] = 15.0f;
  writeMriVolume(dir + "/empty.nii.gz", empty);
  const std::string mri_path = loadMriCaseSource(renderedCase()).path;
  const std::vector<std::tuple<std::string, std::string, std::string>> cases = {
      {"mri: {path: " + dir + "/notes.nii}\n", dir + "/notes.nii", "not an image of a supported format"},
      {"mri: {path: " + dir + "/slice.nii.gz}\n", dir + "/slice.nii.gz", "the MRI must be a 3-D volume"},
      {"mri: {path: " + dir + "/series}\n", "IM00005.dcm", "a slice is missing or the series mixes acquisitions; export the complete series"},
      {"mri: {path: " + dir + "/empty.nii.gz}\n", dir + "/empty.nii.gz", "breast MRI"},
      {"mri: {path: " + mri_path + "}\nlesions: [{name: L9, position_mm: [40, -80, 45]}]\n", mri_path,
       "lesion L9 at (40.0, -80.0, 45.0) mm lies in the air, not in the breast; check its position"},
  };
  for (const auto& [text, names, fix] : cases) {
    SCOPED_TRACE(text);
    const std::string file = dir + "/case.yaml";
    std::ofstream(file) << text;
    {
      std::lock_guard<std::mutex> l(m);
      stages_seen.clear();
    }
    const breast_sim::LoadCase::Response r = load(file, 0);
    EXPECT_FALSE(r.success);
    EXPECT_NE(r.message.find(file), std::string::npos) << r.message;
    EXPECT_NE(r.message.find(names), std::string::npos) << r.message;
    EXPECT_NE(r.message.find(fix), std::string::npos) << r.message;
    // The answer comes when the job ends; ~state says so on its own topic, soon after.
    const std::string fix_text = fix;
    EXPECT_TRUE(waitUntil(
        [&] {
          return state->state == breast_sim::NodeState::IDLE && state->message.find(fix_text) != std::string::npos;
        },
        30.0));
    std::lock_guard<std::mutex> l(m);
    EXPECT_NE(state->message.find("the previous model stays"), std::string::npos) << state->message;
    EXPECT_EQ(state->case_name, "victre_mri_case");
    EXPECT_TRUE(state->model_loaded && state->precomputed);
    EXPECT_EQ(state->stage, "done");
    EXPECT_TRUE(lesions->valid);
  }
  {
    std::lock_guard<std::mutex> l(m);
    // The last load read the MRI and failed in its segmentation.
    EXPECT_NE(std::find(stages_seen.begin(), stages_seen.end(), "segmentation"), stages_seen.end());
  }
  const breast_sim::WriteSupineMri::Response still = writeSupine("after_bad_inputs.nii.gz", true);
  EXPECT_TRUE(still.success) << still.message;
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "mri_case_test");
  ros::NodeHandle nh;
  const breast_sim::test_fixtures::NodeStateFolder state_folder;
  ros::Subscriber s1 = nh.subscribe("/breast_sim/state", 100, onState);
  ros::Subscriber s2 = nh.subscribe("/breast_sim/lesions", 10, onLesions);
  ros::Subscriber s3 = nh.subscribe("/breast_sim/deformed_mesh", 2, onMesh);
  ros::AsyncSpinner spinner(1);
  spinner.start();
  if (!ros::service::waitForService("/breast_sim/write_supine_mri", ros::Duration(60.0))) return 1;
  const int result = RUN_ALL_TESTS();
  ros::shutdown();
  return result;
}
