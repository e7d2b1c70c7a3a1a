#include "yaml_fields.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <sstream>
#include <stdexcept>
#include <vector>

namespace breast_sim::core::yaml_fields {

void fail(const std::string& file, const std::string& key, const std::string& what) {
  throw std::runtime_error(file + ": '" + key + "': " + what);
}

double number(const YAML::Node& n, const std::string& file, const std::string& key) {
  double v = 0.0;
  try {
    v = n.as<double>();
  } catch (const YAML::Exception&) {
    fail(file, key, "expected a number, got '" + YAML::Dump(n) + "'");
  }
  if (!std::isfinite(v)) fail(file, key, "expected a finite number, got '" + YAML::Dump(n) + "'");
  return v;
}

double numberIn(const YAML::Node& n, const std::string& file, const std::string& key, double lo, double hi,
                bool lo_open, bool hi_open, const std::string& unit) {
  const double v = number(n, file, key);
  if (v < lo || v > hi || (lo_open && v == lo) || (hi_open && v == hi)) {
    std::ostringstream s;
    s << "expected a value in " << (lo_open ? "(" : "[") << lo << ", " << hi << (hi_open ? ")" : "]")
      << (unit.empty() ? "" : " " + unit) << ", got " << YAML::Dump(n);
    fail(file, key, s.str());
  }
  return v;
}

std::string text(const YAML::Node& n, const std::string& file, const std::string& key) {
  if (!n.IsScalar()) fail(file, key, "expected a text value, got '" + YAML::Dump(n) + "'");
  return n.as<std::string>();
}

std::string pathBeside(const std::string& file, const std::string& path) {
  if (path.empty()) return path;
  std::filesystem::path p = path;
  if (p.is_relative()) p = std::filesystem::absolute(std::filesystem::path(file).parent_path() / p);
  return p.lexically_normal().string();
}

bool isTargetKeyword(const std::string& target) { return target == "phantom" || target == "auto"; }

std::string choice(const YAML::Node& n, const std::string& file, const std::string& key,
                   const std::set<std::string>& choices) {
  const std::string v = text(n, file, key);
  if (!choices.count(v)) {
    std::string list;
    for (const auto& c : choices) list += (list.empty() ? "" : ", ") + c;
    fail(file, key, "expected one of " + list + ", got '" + v + "'");
  }
  return v;
}

long integer(const YAML::Node& n, const std::string& file, const std::string& key, long lo, long hi) {
  const double v = number(n, file, key);
  if (v != std::floor(v) || v < lo || v > hi)
    fail(file, key, "expected a whole number in [" + std::to_string(lo) + ", " + std::to_string(hi) + "], got '" +
                        YAML::Dump(n) + "'");
  return static_cast<long>(v);
}

bool boolean(const YAML::Node& n, const std::string& file, const std::string& key) {
  try {
    return n.as<bool>();
  } catch (const YAML::Exception&) {
    fail(file, key, "expected true or false, got '" + YAML::Dump(n) + "'");
  }
}

Eigen::Vector3d vec3(const YAML::Node& n, const std::string& file, const std::string& key, const std::string& unit) {
  if (!n.IsSequence() || n.size() != 3)
    fail(file, key, "expected [x, y, z]" + (unit.empty() ? "" : " in " + unit) + ", got '" + YAML::Dump(n) + "'");
  return Eigen::Vector3d(number(n[0], file, key), number(n[1], file, key), number(n[2], file, key));
}

std::string key(const YAML::Node& k, const std::string& file, const std::string& section) {
  if (!k.IsScalar()) {
    YAML::Emitter e;
    e << YAML::Flow << k;
    fail(file, section, "a key is " + std::string(e.c_str()).substr(0, 60) + "; keys must be plain words");
  }
  return k.Scalar();
}

void checkKeys(const YAML::Node& map, const std::set<std::string>& allowed, const std::string& file,
               const std::string& section) {
  if (!map.IsMap()) fail(file, section, "expected a map of keys");
  for (const auto& kv : map) {
    const std::string k = key(kv.first, file, section);
    if (!allowed.count(k)) {
      std::string list;
      for (const auto& a : allowed) list += (list.empty() ? "" : ", ") + a;
      fail(file, section + "." + k, "unknown key; the keys of '" + section + "' are: " + list);
    }
  }
}

namespace {

/// `over`'s keys into a copy of `base`: maps merge key by key, anything else is replaced.
YAML::Node merged(const YAML::Node& base, const YAML::Node& over, const std::string& file,
                  const std::string& section) {
  if (!base.IsMap() || !over.IsMap()) return YAML::Clone(over);
  YAML::Node out = YAML::Clone(base);
  for (const auto& kv : over) {
    const std::string k = key(kv.first, file, section);
    const YAML::Node b = out[k];
    out[k] = b && b.IsMap() && kv.second.IsMap() ? merged(b, kv.second, file, section.empty() ? k : section + "." + k)
                                                 : YAML::Clone(kv.second);
  }
  return out;
}

/// The file-valued keys of a case file: a relative path in a base file is relative to the base's
/// folder, so it is made absolute before the base is merged (the keys of the file given are resolved
/// against it by their readers).
void anchorPaths(YAML::Node& root, const std::string& file) {
  static const std::pair<const char*, const char*> kPathKeys[] = {{"image", "path"}, {"mesh", "path"},
                                                                  {"mri", "path"},   {"mri", "lesion_labels"},
                                                                  {"mri", "truth"},  {"morphing", "target"}};
  if (!root.IsMap()) return;
  for (const auto& [section, key] : kPathKeys) {
    YAML::Node m = root[section];
    if (!m || !m.IsMap() || !m[key] || !m[key].IsScalar()) continue;  // wrong types: the readers name them
    const std::string v = m[key].Scalar();
    if (std::string(key) == "target" && isTargetKeyword(v)) continue;
    m[key] = pathBeside(file, v);
  }
}

YAML::Node loadWithBase(const std::string& path, std::vector<std::string>& chain) {
  const std::string of = chain.empty() ? std::string() : " (the base of " + chain.back() + ")";
  std::error_code ec;
  const auto status = std::filesystem::status(path, ec);
  if (ec || !std::filesystem::exists(status)) throw std::runtime_error(path + ": no such file" + of);
  if (std::filesystem::is_directory(status)) throw std::runtime_error(path + ": is a folder, not a case file" + of);
  if (!std::filesystem::is_regular_file(status))
    throw std::runtime_error(path + ": is not a regular file (a device, a pipe or a socket)" + of);
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::Exception& e) {
    throw std::runtime_error(path + ":" + std::to_string(e.mark.line + 1) + ": not valid YAML: " + e.msg);
  }
  if (!root.IsMap() || !root["base"]) return root;
  const YAML::Node b = root["base"];
  if (!b.IsScalar() || b.as<std::string>().empty())
    fail(path, "base", "expected the file name of a case file to start from (relative to this file's folder)");
  std::filesystem::path base_path;
  std::error_code canonical_error;
  base_path = std::filesystem::weakly_canonical(std::filesystem::path(path).parent_path() / b.Scalar(), canonical_error);
  if (canonical_error) fail(path, "base", "'" + b.Scalar() + "' cannot be resolved (" + canonical_error.message() + ")");
  chain.push_back(std::filesystem::weakly_canonical(path, canonical_error).string());
  if (std::find(chain.begin(), chain.end(), base_path.string()) != chain.end())
    fail(path, "base", "'" + b.as<std::string>() + "' is this file or one of its own bases (a cycle)");
  if (chain.size() > 8) fail(path, "base", "more than 8 files deep; flatten the chain of bases");
  YAML::Node base = loadWithBase(base_path.string(), chain);
  if (!base.IsMap())
    fail(path, "base", "'" + b.as<std::string>() + "' is not a map of keys (empty, or a list); name a case file");
  anchorPaths(base, base_path.string());
  chain.pop_back();
  root.remove("base");
  return merged(base, root, path, "");
}

}  // namespace

std::string caseSource(const YAML::Node& root, const std::string& file) {
  if (!root.IsMap()) throw std::runtime_error(file + ": expected a map with 'phantom:', 'image:', 'mesh:' or 'mri:' at the top");
  std::string found;
  int count = 0;
  for (const char* key : {"phantom", "image", "mesh", "mri"})
    if (root[key]) found = key, ++count;
  if (count != 1)
    throw std::runtime_error(file + ": give exactly one of 'phantom:' (the software phantom), 'image:' (a label image), "
                                    "'mesh:' (a tetrahedral mesh) or 'mri:' (a prone T1 MRI), found " +
                             (count == 0 ? "none" : std::to_string(count)));
  return found;
}

YAML::Node loadFile(const std::string& path) {
  std::vector<std::string> chain;
  return loadWithBase(path, chain);
}

}  // namespace breast_sim::core::yaml_fields
