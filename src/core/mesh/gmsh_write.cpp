// Gmsh MSH 2.2 and 4.1 writer, ASCII and binary; the reader is gmsh_read.cpp.
// Format reference: Gmsh reference manual, section "MSH file format" (4.1) and "Legacy formats" (2.2).

#include <algorithm>
#include <cstdint>
#include <initializer_list>
#include <map>
#include <string>
#include <vector>

#include "breast_sim/core/mesh/mesh_io_detail.h"
#include "gmsh_element_types.h"

namespace breast_sim::core {
namespace {

using gmsh_detail::kTet4;
using mesh_io_detail::appendBinary;
using mesh_io_detail::appendInteger;
using mesh_io_detail::appendReal;

void appendLine(std::string& out, std::initializer_list<long long> values) {
  bool first = true;
  for (long long v : values) {
    if (!first) out += ' ';
    appendInteger(out, v);
    first = false;
  }
  out += '\n';
}

void appendNodeText(std::string& out, long long tag, const TetMesh& mesh, int i, double unit) {
  appendInteger(out, tag);
  for (int k = 0; k < 3; ++k) {
    out += ' ';
    appendReal(out, mesh.nodes()(i, k) / unit);
  }
  out += '\n';
}

void writeGmsh22(std::string& out, const TetMesh& mesh, bool binary, double unit) {
  const int n = mesh.numNodes();
  const int t = mesh.numTets();
  out += binary ? "$MeshFormat\n2.2 1 8\n" : "$MeshFormat\n2.2 0 8\n";
  if (binary) {
    appendBinary(out, 1);
    out += '\n';
  }
  out += "$EndMeshFormat\n$Nodes\n";
  appendLine(out, {n});
  for (int i = 0; i < n; ++i) {
    if (binary) {
      appendBinary(out, i + 1);
      for (int k = 0; k < 3; ++k) appendBinary(out, mesh.nodes()(i, k) / unit);
    } else {
      appendNodeText(out, i + 1, mesh, i, unit);
    }
  }
  if (binary) out += '\n';
  out += "$EndNodes\n$Elements\n";
  appendLine(out, {t});
  // Two tags: physical = elementary = the region label.
  if (binary && t > 0) {
    appendBinary(out, kTet4);
    appendBinary(out, t);
    appendBinary(out, 2);
  }
  for (int e = 0; e < t; ++e) {
    const int label = mesh.regionLabels()[e];
    const auto& tet = mesh.tets().row(e);
    if (binary) {
      for (int v : {e + 1, label, label, tet(0) + 1, tet(1) + 1, tet(2) + 1, tet(3) + 1}) appendBinary(out, v);
    } else {
      appendLine(out, {e + 1, kTet4, 2, label, label, tet(0) + 1, tet(1) + 1, tet(2) + 1, tet(3) + 1});
    }
  }
  if (binary) out += '\n';
  out += "$EndElements\n";
}

void writeGmsh41(std::string& out, const TetMesh& mesh, bool binary, double unit) {
  const int n = mesh.numNodes();
  const int t = mesh.numTets();
  // One volume entity per region label (tags 1, 2, … in label order), its physical tag the label.
  std::map<int, std::vector<int>> by_label;
  for (int e = 0; e < t; ++e) by_label[mesh.regionLabels()[e]].push_back(e);
  auto size = [](std::size_t v) { return static_cast<std::uint64_t>(v); };

  out += binary ? "$MeshFormat\n4.1 1 8\n" : "$MeshFormat\n4.1 0 8\n";
  if (binary) {
    appendBinary(out, 1);
    out += '\n';
  }
  out += "$EndMeshFormat\n$Entities\n";
  const std::size_t volumes = std::max<std::size_t>(by_label.size(), 1);
  if (binary) {
    for (std::size_t c : {std::size_t{0}, std::size_t{0}, std::size_t{0}, volumes}) appendBinary(out, size(c));
  } else {
    appendLine(out, {0, 0, 0, static_cast<long long>(volumes)});
  }
  auto appendVolume = [&](int tag, const std::vector<int>* tets, const int* label) {
    Eigen::Vector3d lo = Eigen::Vector3d::Zero(), hi = Eigen::Vector3d::Zero();
    bool any = false;
    auto grow = [&](int v) {
      const Eigen::Vector3d p = mesh.nodes().row(v).transpose() / unit;
      lo = any ? lo.cwiseMin(p) : p;
      hi = any ? hi.cwiseMax(p) : p;
      any = true;
    };
    if (tets) {
      for (int e : *tets)
        for (int k = 0; k < 4; ++k) grow(mesh.tets()(e, k));
    } else {
      for (int v = 0; v < n; ++v) grow(v);
    }
    if (binary) {
      appendBinary(out, tag);
      for (int k = 0; k < 3; ++k) appendBinary(out, lo(k));
      for (int k = 0; k < 3; ++k) appendBinary(out, hi(k));
      appendBinary(out, size(label ? 1 : 0));
      if (label) appendBinary(out, *label);
      appendBinary(out, size(0));
    } else {
      appendInteger(out, tag);
      for (int k = 0; k < 6; ++k) {
        out += ' ';
        appendReal(out, k < 3 ? lo(k) : hi(k - 3));
      }
      out += label ? " 1 " + std::to_string(*label) + " 0\n" : " 0 0\n";
    }
  };
  if (by_label.empty()) {
    appendVolume(1, nullptr, nullptr);
  } else {
    int tag = 1;
    for (const auto& [label, tets] : by_label) appendVolume(tag++, &tets, &label);
  }
  if (binary) out += '\n';
  out += "$EndEntities\n$Nodes\n";
  // All nodes in one block on volume 1.
  if (binary) {
    for (std::size_t c : {std::size_t{1}, std::size_t(n), std::size_t{1}, std::size_t(n)}) appendBinary(out, size(c));
    appendBinary(out, 3);
    appendBinary(out, 1);
    appendBinary(out, 0);
    appendBinary(out, size(n));
    for (int i = 0; i < n; ++i) appendBinary(out, size(i + 1));
    for (int i = 0; i < n; ++i)
      for (int k = 0; k < 3; ++k) appendBinary(out, mesh.nodes()(i, k) / unit);
    out += '\n';
  } else {
    appendLine(out, {1, n, 1, n});
    appendLine(out, {3, 1, 0, n});
    for (int i = 0; i < n; ++i) appendLine(out, {i + 1});
    for (int i = 0; i < n; ++i) {
      for (int k = 0; k < 3; ++k) {
        if (k) out += ' ';
        appendReal(out, mesh.nodes()(i, k) / unit);
      }
      out += '\n';
    }
  }
  out += "$EndNodes\n$Elements\n";
  // Element tag = tet index + 1, grouped by label; readers sort them back by tag.
  if (binary) {
    for (std::size_t c : {by_label.size(), std::size_t(t), std::size_t{1}, std::size_t(t)}) appendBinary(out, size(c));
  } else {
    appendLine(out, {static_cast<long long>(by_label.size()), t, 1, t});
  }
  int entity = 1;
  for (const auto& [label, tets] : by_label) {
    if (binary) {
      appendBinary(out, 3);
      appendBinary(out, entity);
      appendBinary(out, kTet4);
      appendBinary(out, size(tets.size()));
      for (int e : tets) {
        appendBinary(out, size(e + 1));
        for (int k = 0; k < 4; ++k) appendBinary(out, size(mesh.tets()(e, k) + 1));
      }
    } else {
      appendLine(out, {3, entity, kTet4, static_cast<long long>(tets.size())});
      for (int e : tets) {
        const auto& tet = mesh.tets().row(e);
        appendLine(out, {e + 1, tet(0) + 1, tet(1) + 1, tet(2) + 1, tet(3) + 1});
      }
    }
    ++entity;
  }
  if (binary) out += '\n';
  out += "$EndElements\n";
}

}  // namespace

void writeGmsh(const std::string& path, const TetMesh& mesh, const GmshOptions& options, double length_unit_m) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "writeGmsh");
  std::string out;
  // Rough size so big meshes do not reallocate often: ~60 bytes per node and per element in text.
  out.reserve(64 * static_cast<std::size_t>(mesh.numNodes() + mesh.numTets()) + 1024);
  if (options.version == GmshVersion::kMsh41) {
    writeGmsh41(out, mesh, options.binary, length_unit_m);
  } else {
    writeGmsh22(out, mesh, options.binary, length_unit_m);
  }
  mesh_io_detail::writeFile(path, out);
}

}  // namespace breast_sim::core
