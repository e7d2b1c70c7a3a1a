// The binary state file (pipeline/state_file.h): a reader that checks everything before it keeps
// anything, and an atomic writer.
#include "breast_sim/core/pipeline/state_file.h"

#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>

#include <fcntl.h>
#include <unistd.h>

#include "../util/number_text.h"

namespace breast_sim::core {
namespace {

constexpr char kMagic[8] = {'B', 'S', 'S', 'T', 'A', 'T', 'E', '1'};
constexpr int kHeaderValues = 10;

using util::numberText;

/// The file's bytes with a read position; every read is checked against the end.
class StateReader {
 public:
  explicit StateReader(const std::string& path) : path_(path) {
    std::error_code ec;
    const auto status = std::filesystem::status(path, ec);
    if (ec || !std::filesystem::exists(status)) fail("cannot open the state file (no such file)");
    if (std::filesystem::is_directory(status)) fail("is a folder, not a state file");
    if (!std::filesystem::is_regular_file(status)) fail("is not a regular file (a device or a pipe?)");
    std::ifstream in(path, std::ios::binary);
    if (!in) fail(std::string("cannot open the state file (") + std::strerror(errno) + ")");
    std::ostringstream bytes;
    bytes << in.rdbuf();
    if (in.bad()) fail("read error");
    data_ = bytes.str();
  }

  [[noreturn]] void fail(const std::string& what) const { throw std::runtime_error(path_ + ": " + what); }

  void magic() {
    if (data_.size() < sizeof kMagic || std::memcmp(data_.data(), kMagic, sizeof kMagic) != 0)
      fail("not a breast_sim state file (written by saveState / the node's save_state)");
    pos_ = sizeof kMagic;
  }

  bool atEnd() const { return pos_ == data_.size(); }
  std::size_t bytesLeft() const { return data_.size() - pos_; }
  std::size_t pos() const { return pos_; }

  /// One section: its count, checked against the bytes left before the values are allocated.
  Eigen::VectorXd section(const char* what) {
    const std::size_t at = pos_;
    if (bytesLeft() < sizeof(std::int64_t))
      fail(std::string("truncated state file: the ") + what + " section is missing (the file ends at byte " +
           std::to_string(data_.size()) + ")");
    std::int64_t n = 0;
    std::memcpy(&n, data_.data() + pos_, sizeof n);
    pos_ += sizeof n;
    const std::size_t most = bytesLeft() / sizeof(double);
    if (n < 0 || static_cast<std::uint64_t>(n) > most)
      fail("corrupt state file: the " + std::string(what) + " section at byte " + std::to_string(at) + " says " +
           std::to_string(n) + " values, but " + std::to_string(bytesLeft()) + " bytes (" + std::to_string(most) +
           " values) follow");
    Eigen::VectorXd v(static_cast<Eigen::Index>(n));
    if (n > 0) std::memcpy(v.data(), data_.data() + pos_, static_cast<std::size_t>(n) * sizeof(double));
    pos_ += static_cast<std::size_t>(n) * sizeof(double);
    for (Eigen::Index i = 0; i < v.size(); ++i) {
      if (!std::isfinite(v[i]))
        fail("corrupt state file: value " + std::to_string(i) + " of the " + what + " section is " + numberText(v[i]) +
             "; a state holds finite numbers only");
    }
    return v;
  }

 private:
  std::string path_;
  std::string data_;
  std::size_t pos_ = 0;
};

/// A header value that must be a whole number in [lo, hi] (checked before any integer conversion).
long long wholeNumber(const StateReader& r, double v, const char* what, double lo, double hi) {
  if (!(v >= lo && v <= hi) || v != std::floor(v))
    r.fail("corrupt state file header: " + std::string(what) + " is " + numberText(v) + ", expected a whole number in [" +
           numberText(lo) + ", " + numberText(hi) + "]");
  return static_cast<long long>(v);
}

void requireSize(const StateReader& r, const Eigen::VectorXd& v, Eigen::Index expected, const char* what,
                 const std::string& because) {
  if (v.size() != expected)
    r.fail("corrupt state file: the " + std::string(what) + " section has " + std::to_string(v.size()) +
           " values, expected " + std::to_string(expected) + " (" + because + ")");
}

Points rows3(const StateReader& r, const Eigen::VectorXd& v, const char* what) {
  if (v.size() % 3 != 0)
    r.fail("corrupt state file: the " + std::string(what) + " section has " + std::to_string(v.size()) +
           " values, not a multiple of 3 (x, y, z per node)");
  Points p(v.size() / 3, 3);
  for (Eigen::Index i = 0; i < p.rows(); ++i) p.row(i) = v.segment<3>(3 * i).transpose();
  return p;
}

Eigen::VectorXd flatten(const Points& p) {
  Eigen::VectorXd v(3 * p.rows());
  for (Eigen::Index i = 0; i < p.rows(); ++i) v.segment<3>(3 * i) = p.row(i).transpose();
  return v;
}

void appendSection(std::string& out, const double* data, std::int64_t n) {
  out.append(reinterpret_cast<const char*>(&n), sizeof n);
  if (n > 0) out.append(reinterpret_cast<const char*>(data), static_cast<std::size_t>(n) * sizeof(double));
}

void appendSection(std::string& out, const Eigen::VectorXd& v) { appendSection(out, v.data(), v.size()); }

}  // namespace

StateFile readStateFile(const std::string& path) {
  StateReader r(path);
  r.magic();
  const Eigen::VectorXd h = r.section("header");
  requireSize(r, h, kHeaderValues, "header", "nodes, tets, time, step, alpha, phase, rate, oscillations, stage, fingerprint");
  const Eigen::VectorXd runs = r.section("runs");
  requireSize(r, runs, 3, "runs", "the alpha controller's last three runs");

  constexpr double kIntMax = std::numeric_limits<int>::max();
  StateFile f;
  f.nodes = static_cast<int>(wholeNumber(r, h[0], "the node count", 0, kIntMax));
  f.tets = static_cast<int>(wholeNumber(r, h[1], "the element count", 0, kIntMax));
  PipelineState& s = f.state;
  s.simulation.time_s = h[2];
  // Steps are counted in a long; 2^53 keeps the double exact.
  s.simulation.step = static_cast<long>(wholeNumber(r, h[3], "the step", 0, 9007199254740992.0));
  if (!(h[4] >= 0.0)) r.fail("corrupt state file header: alpha is " + numberText(h[4]) + " 1/Pa, expected >= 0");
  s.alpha.alpha_per_pa = h[4];
  s.alpha.phase = wholeNumber(r, h[5], "the alpha phase (0 search, 1 settling)", 0, 1) == 1
                      ? AlphaController::Phase::kSettling
                      : AlphaController::Phase::kSearch;
  s.alpha.rate = h[6];
  s.alpha.oscillations = static_cast<int>(wholeNumber(r, h[7], "the oscillation count", 0, kIntMax));
  s.stage = static_cast<PipelineStage>(
      wholeNumber(r, h[8], "the stage", 0, static_cast<double>(static_cast<int>(PipelineStage::kDone))));
  f.mesh_fingerprint = h[9];
  for (int k = 0; k < 3; ++k) s.alpha.runs[k] = static_cast<int>(wholeNumber(r, runs[k], "a run direction", -1, 1));

  const Eigen::Index n3 = 3 * static_cast<Eigen::Index>(f.nodes);
  const std::string per_node = std::to_string(f.nodes) + " nodes in the header";
  s.simulation.displacement_m = r.section("displacement");
  requireSize(r, s.simulation.displacement_m, n3, "displacement", per_node);
  s.simulation.velocity_mps = r.section("velocity");
  requireSize(r, s.simulation.velocity_mps, n3, "velocity", per_node);
  s.modulus_factors = r.section("modulus factor");
  requireSize(r, s.modulus_factors, f.tets, "modulus factor", std::to_string(f.tets) + " elements in the header");
  for (Eigen::Index t = 0; t < s.modulus_factors.size(); ++t) {
    if (!(s.modulus_factors[t] > 0.0))
      r.fail("corrupt state file: the modulus factor of element " + std::to_string(t) + " is " +
             numberText(s.modulus_factors[t]) + ", expected > 0");
  }
  s.sliding_targets_m = rows3(r, r.section("sliding target"), "sliding target");
  s.morphing_forces_n = rows3(r, r.section("morphing force"), "morphing force");
  s.sliding_slip_directions.resize(0, 3);
  if (!r.atEnd()) {
    s.sliding_slip_directions = rows3(r, r.section("slip direction"), "slip direction");
    if (s.sliding_slip_directions.rows() != 0 && s.sliding_slip_directions.rows() != s.sliding_targets_m.rows())
      r.fail("corrupt state file: " + std::to_string(s.sliding_slip_directions.rows()) + " slip directions for " +
             std::to_string(s.sliding_targets_m.rows()) + " sliding targets");
  }
  if (!r.atEnd()) {
    const Eigen::VectorXd g = r.section("gravity load");
    requireSize(r, g, 3, "gravity load", "x, y, z in m/s^2");
    s.gravity_load_mps2 = g;
    f.has_gravity_load = true;
  }
  if (!r.atEnd()) {
    const Eigen::VectorXd rest = r.section("rest shape");
    requireSize(r, rest, n3, "rest shape", per_node);
    f.rest_m = rows3(r, rest, "rest shape");
    f.has_rest_shape = true;
  }
  s.element_alpha_per_pa.resize(0);
  if (!r.atEnd()) {
    s.element_alpha_per_pa = r.section("local alpha");
    if (s.element_alpha_per_pa.size() != 0)
      requireSize(r, s.element_alpha_per_pa, f.tets, "local alpha", std::to_string(f.tets) + " elements in the header, or none");
    for (Eigen::Index t = 0; t < s.element_alpha_per_pa.size(); ++t) {
      if (!(s.element_alpha_per_pa[t] >= 0.0))
        r.fail("corrupt state file: the local alpha of element " + std::to_string(t) + " is " +
               numberText(s.element_alpha_per_pa[t]) + " 1/Pa, expected >= 0");
    }
  }
  if (!r.atEnd())
    r.fail("corrupt state file: " + std::to_string(r.bytesLeft()) + " bytes follow the last section (at byte " +
           std::to_string(r.pos()) + ")");
  return f;
}

void writeStateFile(const std::string& path, const StateFile& f) {
  const PipelineState& s = f.state;
  const Eigen::Index n3 = 3 * static_cast<Eigen::Index>(f.nodes);
  if (f.nodes < 0 || f.tets < 0 || s.simulation.displacement_m.size() != n3 || s.simulation.velocity_mps.size() != n3 ||
      s.modulus_factors.size() != f.tets || !f.has_gravity_load || !f.has_rest_shape || f.rest_m.rows() != f.nodes ||
      (s.sliding_slip_directions.rows() != 0 && s.sliding_slip_directions.rows() != s.sliding_targets_m.rows()) ||
      (s.element_alpha_per_pa.size() != 0 &&
       (s.element_alpha_per_pa.size() != f.tets || !s.element_alpha_per_pa.allFinite() || s.element_alpha_per_pa.minCoeff() < 0.0)))
    throw std::invalid_argument("writeStateFile: " + path + ": the state's sizes do not match its " +
                                std::to_string(f.nodes) + " nodes and " + std::to_string(f.tets) +
                                " elements, its gravity load or rest shape is missing, or a local alpha is negative or "
                                "not finite");
  std::string out(kMagic, sizeof kMagic);
  const double header[kHeaderValues] = {static_cast<double>(f.nodes),
                                        static_cast<double>(f.tets),
                                        s.simulation.time_s,
                                        static_cast<double>(s.simulation.step),
                                        s.alpha.alpha_per_pa,
                                        static_cast<double>(s.alpha.phase == AlphaController::Phase::kSettling),
                                        s.alpha.rate,
                                        static_cast<double>(s.alpha.oscillations),
                                        static_cast<double>(static_cast<int>(s.stage)),
                                        f.mesh_fingerprint};
  appendSection(out, header, kHeaderValues);
  const double runs[3] = {static_cast<double>(s.alpha.runs[0]), static_cast<double>(s.alpha.runs[1]),
                          static_cast<double>(s.alpha.runs[2])};
  appendSection(out, runs, 3);
  appendSection(out, s.simulation.displacement_m);
  appendSection(out, s.simulation.velocity_mps);
  appendSection(out, s.modulus_factors);
  appendSection(out, flatten(s.sliding_targets_m));
  appendSection(out, flatten(s.morphing_forces_n));
  appendSection(out, flatten(s.sliding_slip_directions));
  appendSection(out, s.gravity_load_mps2.data(), 3);
  appendSection(out, flatten(f.rest_m));
  appendSection(out, s.element_alpha_per_pa);

  // A temporary beside the target, renamed over it once complete: a crash mid-write leaves the old
  // file (or none), never half a state. open() with 0666 lets the umask set the mode as for any file.
  static std::atomic<unsigned> counter{0};
  std::string tmp;
  int fd = -1;
  for (int attempt = 0; attempt < 100 && fd < 0; ++attempt) {
    tmp = path + ".tmp" + std::to_string(::getpid()) + "_" + std::to_string(counter++);
    fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
    if (fd < 0 && errno != EEXIST) break;
  }
  if (fd < 0)
    throw std::runtime_error(path + ": cannot write the state file (" + std::strerror(errno) +
                             "; check the folder exists and is writable)");
  std::size_t done = 0;
  int error = 0;
  while (done < out.size()) {
    const ssize_t put = ::write(fd, out.data() + done, out.size() - done);
    if (put < 0 && errno == EINTR) continue;
    if (put <= 0) {
      error = put < 0 ? errno : ENOSPC;
      break;
    }
    done += static_cast<std::size_t>(put);
  }
  if (error == 0 && ::fsync(fd) != 0) error = errno;
  if (::close(fd) != 0 && error == 0) error = errno;
  if (error == 0 && std::rename(tmp.c_str(), path.c_str()) != 0) error = errno;
  if (error != 0) {
    std::remove(tmp.c_str());
    throw std::runtime_error(path + ": writing the state file failed (" + std::strerror(error) + ")");
  }
  // The rename reaches the disk with the folder's entry: flushed too, so that after a power loss the
  // name holds the new state, not the old one (or none).
  const std::string folder = std::filesystem::path(path).parent_path().string();
  const int dir = ::open(folder.empty() ? "." : folder.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir >= 0) {
    ::fsync(dir);
    ::close(dir);
  }
}

}  // namespace breast_sim::core
