#pragma once
/// @file vtk_read_detail.h
/// The VTK unstructured-grid readers' shared parts (vtk_legacy_read.cpp, vtu_read.cpp,
/// vtk_mesh_io.cpp); private to src/core/mesh.
///
/// Both formats are parsed here rather than by VTK 9.1's readers, which size their arrays from the
/// counts a file states before reading any data (a few bytes claiming 2·10⁹ points allocate tens of
/// GB) and crash on malformed legacy files (double free, null and out-of-bounds reads in
/// vtkUnstructuredGridReader::ReadMeshSimple). Here every count is checked against the bytes that
/// follow it before anything is allocated, and every cell against the points. VTK still writes
/// both formats, and its compressors (zlib, LZ4, LZMA) inflate the blocks of .vtu files.

#include <cstdint>
#include <string>
#include <vector>

#include "breast_sim/core/mesh/mesh_io_detail.h"

namespace breast_sim::core::vtk_read {

/// A named point or cell array, converted to double (as vtkDataArray::GetComponent gives it).
struct Array {
  std::string name;
  int components = 1;
  std::vector<double> values;  ///< tuples × components, tuple after tuple
};

/// An unstructured grid as a file holds it.
struct Grid {
  std::vector<double> points;             ///< 3 per point, in the file's length unit
  std::vector<std::int64_t> offsets{0};   ///< cell c has connectivity[offsets[c] .. offsets[c+1])
  std::vector<std::int64_t> connectivity; ///< point ids as stored (checked when the mesh is built)
  std::vector<int> types;                 ///< VTK cell type per cell (10: VTK_TETRA)
  std::vector<Array> point_arrays;        ///< one value tuple per point
  std::vector<Array> cell_arrays;         ///< one value tuple per cell

  long long numPoints() const { return static_cast<long long>(points.size() / 3); }
  long long numCells() const { return static_cast<long long>(types.size()); }
};

/// Most points or cells a file may declare: the mesh stores indices as int.
constexpr long long kMaxCount = 2147483647;

/// Binary value types of both formats.
enum class Scalar { kInt8, kUInt8, kInt16, kUInt16, kInt32, kUInt32, kInt64, kUInt64, kFloat32, kFloat64 };

inline std::size_t scalarBytes(Scalar s) {
  switch (s) {
    case Scalar::kInt8: case Scalar::kUInt8: return 1;
    case Scalar::kInt16: case Scalar::kUInt16: return 2;
    case Scalar::kInt32: case Scalar::kUInt32: case Scalar::kFloat32: return 4;
    default: return 8;
  }
}

/// One value at `p` in the given byte order, as a double.
double scalarValue(const char* p, Scalar s, bool big_endian);
/// One integer value at `p`; false for a float type or a value beyond int64.
bool scalarInteger(const char* p, Scalar s, bool big_endian, std::int64_t& value);

/// Adds an array, replacing one of the same name in place (as vtkFieldData::AddArray does).
void addArray(std::vector<Array>& arrays, Array array);

/// Reads a legacy .vtk unstructured grid (file versions 2.0 to 5.1, ASCII or BINARY).
Grid readLegacy(mesh_io_detail::FileCursor& f);
/// Reads a VTK XML .vtu unstructured grid (ascii, inline base64 or appended raw/base64 data;
/// uncompressed or zlib, LZ4 or LZMA blocks; UInt32 or UInt64 headers; either byte order).
Grid readXml(mesh_io_detail::FileCursor& f);

}  // namespace breast_sim::core::vtk_read
