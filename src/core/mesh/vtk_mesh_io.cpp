// VTK unstructured grids: the writers (.vtu XML, .vtk legacy) through the VTK library, and the mesh
// made from what the readers (vtu_read.cpp, vtk_legacy_read.cpp) parse.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

#include <vtkCellArray.h>
#include <vtkCellData.h>
#include <vtkCellType.h>
#include <vtkCommand.h>
#include <vtkDataArray.h>
#include <vtkDoubleArray.h>
#include <vtkIdTypeArray.h>
#include <vtkIntArray.h>
#include <vtkNew.h>
#include <vtkPointData.h>
#include <vtkPoints.h>
#include <vtkSmartPointer.h>
#include <vtkUnstructuredGrid.h>
#include <vtkUnstructuredGridWriter.h>
#include <vtkXMLUnstructuredGridWriter.h>

#include "breast_sim/core/mesh/mesh_io_detail.h"
#include "vtk_read_detail.h"

namespace breast_sim::core {
namespace {

constexpr const char* kRegionArray = "region";
constexpr const char* kNodeSetPrefix = "nodeset_";

/// Collects the error and warning messages of a VTK algorithm instead of letting them go to stderr, so
/// they end up in our exception.
class ErrorCollector : public vtkCommand {
 public:
  static ErrorCollector* New() { return new ErrorCollector; }
  void Execute(vtkObject*, unsigned long event, void* call_data) override {
    if (event == vtkCommand::ErrorEvent) {
      const char* text = static_cast<const char*>(call_data);
      std::string s = text ? text : "unknown VTK error";
      while (!s.empty() && (s.back() == '\n' || s.back() == ' ')) s.pop_back();
      // VTK prefixes "ERROR: In <source file>, line N\n<class> (0x…): "; keep the sentence.
      const std::size_t nl = s.rfind('\n');
      if (nl != std::string::npos) s = s.substr(nl + 1);
      const std::size_t colon = s.find("): ");
      if (colon != std::string::npos && s.compare(0, 3, "vtk") == 0) s = s.substr(colon + 3);
      if (!errors.empty()) errors += "; ";
      errors += s;
    }
  }
  std::string errors;
};

bool startsWith(const std::string& s, const char* prefix) { return s.rfind(prefix, 0) == 0; }

Eigen::MatrixXd arrayValues(const vtk_read::Array& array, const std::vector<std::size_t>* rows) {
  const std::size_t c = static_cast<std::size_t>(array.components);
  const std::size_t n = rows ? rows->size() : array.values.size() / c;
  Eigen::MatrixXd values(static_cast<Eigen::Index>(n), static_cast<Eigen::Index>(c));
  for (std::size_t i = 0; i < n; ++i) {
    const std::size_t row = rows ? (*rows)[i] : i;
    for (std::size_t k = 0; k < c; ++k) values(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(k)) = array.values[row * c + k];
  }
  return values;
}

/// The tetrahedral mesh of a parsed grid: VTK_TETRA cells (others skipped, their ids still
/// checked), region labels, node sets, other arrays as fields.
TetMesh gridToMesh(const std::string& path, const vtk_read::Grid& grid, double unit, MeshFields* fields) {
  const long long n = grid.numPoints();
  Points nodes(n, 3);
  for (long long i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) nodes(i, k) = grid.points[3 * static_cast<std::size_t>(i) + k] * unit;
  }
  std::vector<std::size_t> tet_cells;
  const long long cells = grid.numCells();
  for (long long c = 0; c < cells; ++c) {
    const std::int64_t begin = grid.offsets[c], end = grid.offsets[c + 1];
    for (std::int64_t k = begin; k < end; ++k) {
      // Compared as 64-bit ids: an id beyond int must not wrap onto a valid point.
      const std::int64_t id = grid.connectivity[static_cast<std::size_t>(k)];
      if (id < 0 || id >= n) {
        throw std::runtime_error(path + ": cell " + std::to_string(c) + " refers to point " + std::to_string(id) +
                                 ", but the file has " + std::to_string(n) + " points (ids are 0-based)");
      }
    }
    if (grid.types[c] == VTK_TETRA) {
      if (end - begin != 4) {
        throw std::runtime_error(path + ": tetra cell " + std::to_string(c) + " has " + std::to_string(end - begin) +
                                 " points");
      }
      tet_cells.push_back(static_cast<std::size_t>(c));
    }
  }
  if (tet_cells.empty()) {
    throw std::runtime_error(path + ": no VTK_TETRA cells among its " + std::to_string(cells) + " cells");
  }
  Tets tets(static_cast<Eigen::Index>(tet_cells.size()), 4);
  for (std::size_t t = 0; t < tet_cells.size(); ++t) {
    const std::int64_t begin = grid.offsets[tet_cells[t]];
    for (int k = 0; k < 4; ++k) tets(static_cast<Eigen::Index>(t), k) = static_cast<int>(grid.connectivity[begin + k]);
  }

  // Region labels: the first integer-valued cell array among the accepted names.
  std::vector<int> labels(tet_cells.size(), 0);
  std::string label_name;
  for (const char* name : {"region", "label", "gmsh:physical"}) {
    const auto array = std::find_if(grid.cell_arrays.begin(), grid.cell_arrays.end(),
                                    [&](const vtk_read::Array& a) { return a.name == name; });
    if (array == grid.cell_arrays.end()) continue;
    if (array->components != 1) {
      throw std::runtime_error(path + ": cell array '" + name + "' has " + std::to_string(array->components) +
                               " components; region labels need 1");
    }
    for (std::size_t t = 0; t < tet_cells.size(); ++t) {
      const double v = array->values[tet_cells[t]];
      if (v != std::round(v) || std::abs(v) > std::numeric_limits<int>::max()) {
        throw std::runtime_error(path + ": cell array '" + name + "' holds " + std::to_string(v) + " at cell " +
                                 std::to_string(tet_cells[t]) + "; region labels must be integers");
      }
      labels[t] = static_cast<int>(v);
    }
    label_name = name;
    break;
  }

  // Node sets and other fields.
  std::vector<std::pair<std::string, std::vector<int>>> node_sets;
  for (const vtk_read::Array& array : grid.point_arrays) {
    if (array.name.empty()) continue;
    if (startsWith(array.name, kNodeSetPrefix) && array.name.size() > std::strlen(kNodeSetPrefix)) {
      std::vector<int> set;
      const std::size_t c = static_cast<std::size_t>(array.components);
      for (long long i = 0; i < n; ++i) {
        if (array.values[static_cast<std::size_t>(i) * c] != 0.0) set.push_back(static_cast<int>(i));
      }
      node_sets.emplace_back(array.name.substr(std::strlen(kNodeSetPrefix)), std::move(set));
    } else if (fields) {
      fields->point_data.push_back({array.name, arrayValues(array, nullptr)});
    }
  }
  if (fields) {
    for (const vtk_read::Array& array : grid.cell_arrays) {
      if (array.name.empty() || array.name == label_name) continue;
      fields->cell_data.push_back({array.name, arrayValues(array, &tet_cells)});
    }
  }

  TetMesh mesh = mesh_io_detail::makeMesh(path, std::move(nodes), std::move(tets), std::move(labels));
  for (auto& [name, set] : node_sets) mesh_io_detail::addNodeSet(path, mesh, name, std::move(set));
  return mesh;
}

}  // namespace

namespace vtk_read {

void addArray(std::vector<Array>& arrays, Array array) {
  for (Array& a : arrays) {
    if (a.name == array.name) {
      a = std::move(array);
      return;
    }
  }
  arrays.push_back(std::move(array));
}

namespace {
template <typename T>
T load(const char* p, bool big_endian) {
  unsigned char b[sizeof(T)];
  std::memcpy(b, p, sizeof(T));
  const std::uint16_t one = 1;
  const bool host_big = *reinterpret_cast<const unsigned char*>(&one) == 0;
  if (big_endian != host_big) std::reverse(b, b + sizeof(T));
  T v;
  std::memcpy(&v, b, sizeof(T));
  return v;
}
}  // namespace

double scalarValue(const char* p, Scalar s, bool big_endian) {
  switch (s) {
    case Scalar::kInt8: return load<std::int8_t>(p, big_endian);
    case Scalar::kUInt8: return load<std::uint8_t>(p, big_endian);
    case Scalar::kInt16: return load<std::int16_t>(p, big_endian);
    case Scalar::kUInt16: return load<std::uint16_t>(p, big_endian);
    case Scalar::kInt32: return load<std::int32_t>(p, big_endian);
    case Scalar::kUInt32: return load<std::uint32_t>(p, big_endian);
    case Scalar::kInt64: return static_cast<double>(load<std::int64_t>(p, big_endian));
    case Scalar::kUInt64: return static_cast<double>(load<std::uint64_t>(p, big_endian));
    case Scalar::kFloat32: return load<float>(p, big_endian);
    case Scalar::kFloat64: return load<double>(p, big_endian);
  }
  return 0.0;
}

bool scalarInteger(const char* p, Scalar s, bool big_endian, std::int64_t& value) {
  switch (s) {
    case Scalar::kFloat32:
    case Scalar::kFloat64: return false;
    case Scalar::kUInt64: {
      const std::uint64_t v = load<std::uint64_t>(p, big_endian);
      if (v > static_cast<std::uint64_t>(std::numeric_limits<std::int64_t>::max())) return false;
      value = static_cast<std::int64_t>(v);
      return true;
    }
    case Scalar::kInt64: value = load<std::int64_t>(p, big_endian); return true;
    default: value = static_cast<std::int64_t>(scalarValue(p, s, big_endian)); return true;
  }
}

}  // namespace vtk_read

namespace {

void checkFields(const char* function, const TetMesh& mesh, const MeshFields& fields) {
  auto check = [&](const std::vector<MeshField>& list, const char* kind, Eigen::Index rows, const char* count) {
    std::set<std::string> names;
    for (const MeshField& field : list) {
      const std::string where = std::string(function) + ": " + kind + " field '" + field.name + "'";
      if (field.name.empty()) throw std::invalid_argument(std::string(function) + ": a " + kind + " field has no name");
      if (!names.insert(field.name).second) throw std::invalid_argument(where + " is given twice");
      if (field.values.rows() != rows) {
        throw std::invalid_argument(where + " has " + std::to_string(field.values.rows()) + " rows; expected " +
                                    std::to_string(rows) + " (" + count + ")");
      }
      if (field.values.cols() < 1) throw std::invalid_argument(where + " has no column");
      if (kind == std::string("point") && startsWith(field.name, kNodeSetPrefix)) {
        throw std::invalid_argument(where + ": names starting with 'nodeset_' are reserved for node sets");
      }
      if (kind == std::string("cell") && field.name == kRegionArray) {
        throw std::invalid_argument(where + ": the name 'region' is reserved for the region labels");
      }
    }
  };
  check(fields.point_data, "point", mesh.numNodes(), "one per node");
  check(fields.cell_data, "cell", mesh.numTets(), "one per tetrahedron");
}

vtkSmartPointer<vtkDoubleArray> fieldArray(const MeshField& field, double unit) {
  auto array = vtkSmartPointer<vtkDoubleArray>::New();
  array->SetName(field.name.c_str());
  array->SetNumberOfComponents(static_cast<int>(field.values.cols()));
  array->SetNumberOfTuples(field.values.rows());
  const double scale = field.is_length ? 1.0 / unit : 1.0;
  double* out = array->GetPointer(0);
  const Eigen::Index c = field.values.cols();
  for (Eigen::Index i = 0; i < field.values.rows(); ++i)
    for (Eigen::Index k = 0; k < c; ++k) out[i * c + k] = field.values(i, k) * scale;
  return array;
}

vtkSmartPointer<vtkUnstructuredGrid> meshToGrid(const TetMesh& mesh, const MeshFields& fields, double unit,
                                                const Points* positions_m) {
  const int n = mesh.numNodes();
  const int t = mesh.numTets();
  if (positions_m && (positions_m->rows() != n || !positions_m->allFinite()))
    throw std::invalid_argument("VTK writer: " + std::to_string(positions_m->rows()) +
                                " node positions given for a mesh of " + std::to_string(n) +
                                " nodes (they must be #N finite rows)");
  const Points& x = positions_m ? *positions_m : mesh.nodes();
  vtkNew<vtkPoints> points;
  points->SetDataTypeToDouble();
  points->SetNumberOfPoints(n);
  for (int i = 0; i < n; ++i) {
    points->SetPoint(i, x(i, 0) / unit, x(i, 1) / unit, x(i, 2) / unit);
  }
  vtkNew<vtkIdTypeArray> offsets;
  vtkNew<vtkIdTypeArray> connectivity;
  offsets->SetNumberOfValues(t + 1);
  connectivity->SetNumberOfValues(4 * static_cast<vtkIdType>(t));
  for (int e = 0; e <= t; ++e) offsets->SetValue(e, 4 * static_cast<vtkIdType>(e));
  for (int e = 0; e < t; ++e)
    for (int k = 0; k < 4; ++k) connectivity->SetValue(4 * static_cast<vtkIdType>(e) + k, mesh.tets()(e, k));
  vtkNew<vtkCellArray> cells;
  cells->SetData(offsets, connectivity);

  auto grid = vtkSmartPointer<vtkUnstructuredGrid>::New();
  grid->SetPoints(points);
  grid->SetCells(VTK_TETRA, cells);

  vtkNew<vtkIntArray> region;
  region->SetName(kRegionArray);
  region->SetNumberOfValues(t);
  for (int e = 0; e < t; ++e) region->SetValue(e, mesh.regionLabels()[e]);
  grid->GetCellData()->AddArray(region);
  for (const MeshField& field : fields.cell_data) grid->GetCellData()->AddArray(fieldArray(field, unit));

  for (const MeshField& field : fields.point_data) grid->GetPointData()->AddArray(fieldArray(field, unit));
  for (const auto& [name, nodes] : mesh.nodeSets()) {
    vtkNew<vtkIntArray> mask;
    mask->SetName((kNodeSetPrefix + name).c_str());
    mask->SetNumberOfValues(n);
    mask->FillValue(0);
    for (int v : nodes) mask->SetValue(v, 1);
    grid->GetPointData()->AddArray(mask);
  }
  return grid;
}

}  // namespace

TetMesh readVtkUnstructured(const std::string& path, double length_unit_m, MeshFields* fields) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "readVtkUnstructured");
  const MeshFileFormat format = meshFileFormat(path);
  if (format != MeshFileFormat::kVtu && format != MeshFileFormat::kVtkLegacy) {
    throw std::runtime_error(path + ": readVtkUnstructured reads .vtu and .vtk files only");
  }
  mesh_io_detail::FileCursor f(path);
  const vtk_read::Grid grid = format == MeshFileFormat::kVtu ? vtk_read::readXml(f) : vtk_read::readLegacy(f);
  // Fields are filled only once the whole mesh is good.
  MeshFields read_fields;
  TetMesh mesh = gridToMesh(path, grid, length_unit_m, fields ? &read_fields : nullptr);
  if (fields) *fields = std::move(read_fields);
  return mesh;
}

void writeVtu(const std::string& path, const TetMesh& mesh, const MeshFields& fields, double length_unit_m,
              const VtkOptions& options) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "writeVtu");
  checkFields("writeVtu", mesh, fields);
  auto grid = meshToGrid(mesh, fields, length_unit_m, options.positions_m);
  vtkNew<vtkXMLUnstructuredGridWriter> writer;
  vtkNew<ErrorCollector> errors;
  writer->AddObserver(vtkCommand::ErrorEvent, errors);
  writer->SetInputData(grid);
  writer->SetFileName(path.c_str());
  writer->SetHeaderTypeToUInt64();  // data arrays over 4 GB stay readable
  if (options.binary) {
    writer->SetDataModeToAppended();
    writer->EncodeAppendedDataOff();
    writer->SetCompressorTypeToZLib();
  } else {
    writer->SetDataModeToAscii();
  }
  const int ok = writer->Write();
  if (!ok || !errors->errors.empty()) {
    throw std::runtime_error(path + ": VTK could not write the file" +
                             (errors->errors.empty() ? std::string() : ": " + errors->errors));
  }
}

void writeVtkLegacy(const std::string& path, const TetMesh& mesh, const MeshFields& fields, double length_unit_m,
                    const VtkOptions& options) {
  mesh_io_detail::checkLengthUnit(length_unit_m, "writeVtkLegacy");
  checkFields("writeVtkLegacy", mesh, fields);
  auto grid = meshToGrid(mesh, fields, length_unit_m, options.positions_m);
  vtkNew<vtkUnstructuredGridWriter> writer;
  vtkNew<ErrorCollector> errors;
  writer->AddObserver(vtkCommand::ErrorEvent, errors);
  writer->SetInputData(grid);
  writer->SetFileName(path.c_str());
  // Version 4.2 (CELLS n size with counts) is read by every VTK-based tool, old and new.
  writer->SetFileVersion(vtkUnstructuredGridWriter::VTK_LEGACY_READER_VERSION_4_2);
  if (options.binary) {
    writer->SetFileTypeToBinary();
  } else {
    writer->SetFileTypeToASCII();
  }
  const int ok = writer->Write();
  if (!ok || !errors->errors.empty()) {
    throw std::runtime_error(path + ": VTK could not write the file" +
                             (errors->errors.empty() ? std::string() : ": " + errors->errors));
  }
}

}  // namespace breast_sim::core
