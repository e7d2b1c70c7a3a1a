#pragma once
/// @file yaml_fields.h
/// Checked reading of YAML case and settings files (private to the core): every error names the
/// file, the key and what is expected.

#include <set>
#include <string>

#include <Eigen/Core>
#include <yaml-cpp/yaml.h>

namespace breast_sim::core::yaml_fields {

/// @throws std::runtime_error "FILE: 'KEY': WHAT".
[[noreturn]] void fail(const std::string& file, const std::string& key, const std::string& what);
/// A finite number.
double number(const YAML::Node& n, const std::string& file, const std::string& key);
/// A number in [lo, hi] (bounds included unless open).
double numberIn(const YAML::Node& n, const std::string& file, const std::string& key, double lo, double hi,
                bool lo_open = false, bool hi_open = false, const std::string& unit = "");
std::string text(const YAML::Node& n, const std::string& file, const std::string& key);
/// A path a case file names: relative to the file's folder unless absolute; made absolute and normal.
/// An empty path stays empty.
std::string pathBeside(const std::string& file, const std::string& path);
/// morphing.target's words that name no file ("phantom", "auto"): they are not paths.
bool isTargetKeyword(const std::string& target);
/// One of `choices`.
std::string choice(const YAML::Node& n, const std::string& file, const std::string& key,
                   const std::set<std::string>& choices);
/// A whole number in [lo, hi].
long integer(const YAML::Node& n, const std::string& file, const std::string& key, long lo, long hi);
bool boolean(const YAML::Node& n, const std::string& file, const std::string& key);
/// [x, y, z]; `unit` is named in the error.
Eigen::Vector3d vec3(const YAML::Node& n, const std::string& file, const std::string& key, const std::string& unit = "mm");
/// A map key as text. @throws std::runtime_error naming the file and section when the key is not a
/// plain scalar (a list or a map used as a key).
std::string key(const YAML::Node& k, const std::string& file, const std::string& section);
/// `map` is a map whose keys are all in `allowed` (plain scalars).
void checkKeys(const YAML::Node& map, const std::set<std::string>& allowed, const std::string& file,
               const std::string& section);
/// Which source of tissue a case file's root map names: "phantom", "image", "mesh" or "mri".
/// @throws std::runtime_error naming the file unless exactly one of them is there.
std::string caseSource(const YAML::Node& root, const std::string& file);
/// Loads a YAML file. A top-level `base: FILE` (relative to this file's folder) loads that file first
/// and this file's keys replace its keys, map by map (a map merges into the base's map of the same
/// key, anything else replaces it); bases may have bases (at most 8 deep, no cycles). The `base` key
/// itself is not in the result. A relative path is relative to the folder of the file that names
/// it: a base's file-valued keys (image.path, mesh.path, mri.path, mri.lesion_labels, mri.truth,
/// morphing.target) come back absolute; the readers resolve the top file's own against its folder.
/// @throws std::runtime_error naming the file and line, or the base that cannot be read.
YAML::Node loadFile(const std::string& path);

}  // namespace breast_sim::core::yaml_fields
