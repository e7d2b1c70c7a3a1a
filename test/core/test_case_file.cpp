// The case file's keys, their readers and their documentation agree: effectiveCaseYaml writes every
// key, each reader reads back exactly what was written, the shipped cases keep the code's simulation
// defaults, and docs/case_files.md lists every key with the code's default.
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

#include "breast_sim/core/pipeline/case_file.h"

#include "temp_dir.h"

namespace fs = std::filesystem;
using breast_sim::core::effectiveCaseYaml;
using breast_sim::test::TempDir;

namespace {

const fs::path kSource = fs::path(BREAST_SIM_TEST_DATA_DIR) / ".." / "..";

std::string readFile(const fs::path& p) {
  std::ifstream in(p);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

std::string emit(const YAML::Node& n) {
  YAML::Emitter e;
  e << n;
  return e.c_str();
}

/// The effective case of `text` (a case file's content).
YAML::Node effective(const TempDir& dir, const std::string& text) {
  return YAML::Load(effectiveCaseYaml(dir.write("case.yaml", text)));
}

/// Scalar keys of the settings maps, as section.key.
std::vector<std::pair<std::string, std::string>> scalarKeys(const YAML::Node& root) {
  std::vector<std::pair<std::string, std::string>> keys;
  for (const char* section : {"phantom", "meshing", "simulation", "stiffening", "sliding", "morphing", "coarse_start", "uncertainty"})
    for (const auto& kv : root[section])
      if (kv.second.IsScalar()) keys.emplace_back(section, kv.first.as<std::string>());
  return keys;
}

/// Other values to try for a key: numbers scaled and shifted, booleans flipped, every word the
/// readers take for a choice.
std::vector<std::string> alternatives(const YAML::Node& value) {
  const std::string v = value.as<std::string>();
  if (v == "true") return {"false"};
  if (v == "false") return {"true"};
  try {
    std::size_t used = 0;
    const double x = std::stod(v, &used);
    if (used == v.size()) {
      std::vector<std::string> out;
      for (double c : {x * 1.25, x * 0.8, x + 1, x - 1, x * 2, x * 0.5, 0.5, 1.0, 2.0, 3.0, 0.1, 0.0, x * 1.01, x * 0.99}) {
        std::ostringstream s;
        s.precision(12);
        s << c;
        if (s.str() != v) out.push_back(s.str());
      }
      return out;
    }
  } catch (const std::exception&) {
  }
  std::vector<std::string> words = {"right", "left", "cylindrical", "planar", "anp", "linear", "trace", "determinant",
                                    "aggregation", "cholmod", "jacobi-pcg", "multigrid", "chebyshev", "gauss-seidel", "jacobi",
                                    "explicit", "implicit", "initial", "current", "off_wall", "all_max", "pulled_p95",
                                    "skin", "phantom", "auto", "unloaded", "prone", ""};
  words.erase(std::remove(words.begin(), words.end(), v), words.end());
  return words;
}

}  // namespace

TEST(CaseFile, EffectiveCaseOfEveryShippedCaseReadsBackToItself) {
  TempDir dir("breast_sim_case_file");
  int cases = 0;
  for (const auto& entry : fs::directory_iterator(kSource / "config")) {
    const fs::path p = entry.path();
    if (p.extension() != ".yaml" || p.filename() == "node.yaml") continue;
    SCOPED_TRACE(p.string());
    const std::string first = effectiveCaseYaml(p.string());
    const std::string second = effectiveCaseYaml(dir.write("again.yaml", first));
    EXPECT_EQ(first, second);
    ++cases;
  }
  EXPECT_GE(cases, 5);
}

// Writing a key and reading it must be inverse for each key on its own: a key written under another
// key's name, or read into the wrong field, changes some other key of the re-written case.
TEST(CaseFile, EachKeyIsReadBackAsWrittenAndChangesNothingElse) {
  TempDir dir("breast_sim_case_file");
  const YAML::Node base = effective(dir, "phantom: {}\n");
  int tested = 0;
  std::vector<std::string> untested;
  for (const auto& [section, key] : scalarKeys(base)) {
    bool done = false;
    // Keys that depend on others: a second breast moves the default lesions out of the tissue, and
    // sliding needs stiffening. Each value is tried alone, then without the lesions and the sliding.
    const bool is_sliding = section == "simulation" && key == "sliding";
    std::vector<std::pair<std::string, bool>> tries;
    for (const std::string& alt : alternatives(base[section][key])) tries.emplace_back(alt, false);
    for (const std::string& alt : alternatives(base[section][key])) tries.emplace_back(alt, true);
    for (const auto& [alt, companions] : tries) {
      YAML::Node changed = YAML::Clone(base);
      changed[section][key] = YAML::Load(alt.empty() ? "''" : alt);
      if (companions) {
        changed["phantom"]["lesions"] = YAML::Node(YAML::NodeType::Sequence);
        if (!is_sliding) changed["simulation"]["sliding"] = false;
      }
      YAML::Node back;
      try {
        back = effective(dir, emit(changed));
      } catch (const std::exception&) {
        continue;  // out of range or against another key: try the next value
      }
      SCOPED_TRACE(section + "." + key + " = '" + alt + "'");
      for (const auto& [s2, k2] : scalarKeys(base)) {
        const std::string want = (s2 == section && k2 == key) ? changed[s2][k2].as<std::string>() : base[s2][k2].as<std::string>();
        std::string got = back[s2][k2].as<std::string>();
        // A target file is read relative to the case's folder: compare its name.
        if (s2 == "morphing" && k2 == "target" && fs::path(got).is_absolute()) got = fs::path(got).filename().string();
        if (companions && !is_sliding && s2 == "simulation" && k2 == "sliding") continue;
        EXPECT_EQ(got, want) << "after changing " << section << "." << key << ": " << s2 << "." << k2;
      }
      done = true;
      break;
    }
    if (done) ++tested;
    else untested.push_back(section + "." + key);
  }
  std::string list;
  for (const auto& k : untested) list += k + " ";
  EXPECT_TRUE(untested.empty()) << "keys no other value was accepted for: " << list;
  EXPECT_GE(tested, 100);
}

TEST(CaseFile, ShippedCasesKeepTheCodeDefaultsOfTheSimulation) {
  TempDir dir("breast_sim_case_file");
  const YAML::Node defaults = effective(dir, "phantom: {}\n");
  // The rest shape's default depends on the case: the software phantom's is the prone shape, a
  // patient's image, MRI or mesh the unloaded one (SimulationSettings::resolvedReferenceState).
  EXPECT_EQ(defaults["simulation"]["reference_state"].as<std::string>(), "prone");
  for (const auto& [name, reference] : {std::pair<const char*, const char*>{"phantom_default.yaml", "prone"},
                                        {"victre_case.yaml", "unloaded"},
                                        {"victre_mri_case.yaml", "unloaded"},
                                        {"mesh_case.yaml", "unloaded"}}) {
    SCOPED_TRACE(name);
    const YAML::Node shipped = YAML::Load(effectiveCaseYaml((kSource / "config" / name).string()));
    EXPECT_EQ(shipped["simulation"]["reference_state"].as<std::string>(), reference);
    YAML::Node expected = YAML::Clone(defaults);
    expected["simulation"]["reference_state"] = reference;
    for (const char* section : {"simulation", "stiffening", "sliding"})
      EXPECT_EQ(emit(shipped[section]), emit(expected[section])) << section;
  }
}

// docs/case_files.md holds, in its first yaml block, every key at its default value.
TEST(CaseFile, DocumentedKeysAndDefaultsAreTheCodes) {
  const std::string doc = readFile(kSource / "docs" / "case_files.md");
  const std::size_t open = doc.find("```yaml\n");
  ASSERT_NE(open, std::string::npos) << "docs/case_files.md has no ```yaml block";
  const std::size_t start = open + 8;
  const std::size_t close = doc.find("```", start);
  ASSERT_NE(close, std::string::npos);
  TempDir dir("breast_sim_case_file");
  const std::string documented = effectiveCaseYaml(dir.write("documented.yaml", doc.substr(start, close - start)));
  const std::string defaults = effectiveCaseYaml(dir.write("defaults.yaml", "phantom: {}\n"));
  EXPECT_EQ(documented, defaults);
  // Every key of the code is in the block itself, not only filled in by the reader.
  const YAML::Node block = YAML::Load(doc.substr(start, close - start));
  for (const auto& [section, key] : scalarKeys(YAML::Load(defaults)))
    EXPECT_TRUE(block[section] && block[section][key]) << section << "." << key << " is not documented";
}
