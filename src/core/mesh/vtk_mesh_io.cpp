// VTK unstructured-grid reader and writers (.vtu XML, .vtk legacy) through the VTK library.

#include <cerrno>
#include <cmath>
#include <cstdio>
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
#include <vtkUnstructuredGridReader.h>
#include <vtkUnstructuredGridWriter.h>
#include <vtkXMLUnstructuredGridReader.h>
#include <vtkXMLUnstructuredGridWriter.h>

#include "breast_sim/core/mesh/mesh_io_detail.h"

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

void checkFileReadable(const std::string& path) {
  std::FILE* file = std::fopen(path.c_str(), "rb");
  if (!file) throw std::runtime_error(path + ": cannot open for reading (" + std::strerror(errno) + ")");
  std::fclose(file);
}

Eigen::MatrixXd arrayValues(vtkDataArray* array, const std::vector<vtkIdType>* rows) {
  const int c = array->GetNumberOfComponents();
  const vtkIdType n = rows ? static_cast<vtkIdType>(rows->size()) : array->GetNumberOfTuples();
  Eigen::MatrixXd values(n, c);
  for (vtkIdType i = 0; i < n; ++i) {
    const vtkIdType row = rows ? (*rows)[i] : i;
    for (int k = 0; k < c; ++k) values(i, k) = array->GetComponent(row, k);
  }
  return values;
}

TetMesh gridToMesh(const std::string& path, vtkUnstructuredGrid* grid, double unit, MeshFields* fields) {
  const vtkIdType n = grid->GetNumberOfPoints();
  if (n > std::numeric_limits<int>::max()) throw std::runtime_error(path + ": too many points");
  Points nodes(n, 3);
  for (vtkIdType i = 0; i < n; ++i) {
    double p[3];
    grid->GetPoint(i, p);
    for (int k = 0; k < 3; ++k) nodes(i, k) = p[k] * unit;
  }
  std::vector<vtkIdType> tet_cells;
  const vtkIdType cells = grid->GetNumberOfCells();
  for (vtkIdType c = 0; c < cells; ++c) {
    if (grid->GetCellType(c) == VTK_TETRA) tet_cells.push_back(c);
  }
  if (tet_cells.empty()) {
    throw std::runtime_error(path + ": no VTK_TETRA cells among its " + std::to_string(cells) + " cells");
  }
  Tets tets(static_cast<Eigen::Index>(tet_cells.size()), 4);
  for (std::size_t t = 0; t < tet_cells.size(); ++t) {
    vtkIdType npts = 0;
    const vtkIdType* pts = nullptr;
    grid->GetCellPoints(tet_cells[t], npts, pts);
    if (npts != 4) throw std::runtime_error(path + ": tetra cell " + std::to_string(tet_cells[t]) + " has " +
                                            std::to_string(npts) + " points");
    for (int k = 0; k < 4; ++k) tets(static_cast<Eigen::Index>(t), k) = static_cast<int>(pts[k]);
  }

  // Region labels: the first integer-valued cell array among the accepted names.
  std::vector<int> labels(tet_cells.size(), 0);
  std::string label_name;
  vtkCellData* cd = grid->GetCellData();
  for (const char* name : {"region", "label", "gmsh:physical"}) {
    vtkDataArray* array = cd->GetArray(name);
    if (!array) continue;
    if (array->GetNumberOfComponents() != 1) {
      throw std::runtime_error(path + ": cell array '" + name + "' has " +
                               std::to_string(array->GetNumberOfComponents()) + " components; region labels need 1");
    }
    for (std::size_t t = 0; t < tet_cells.size(); ++t) {
      const double v = array->GetComponent(tet_cells[t], 0);
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
  vtkPointData* pd = grid->GetPointData();
  std::vector<std::pair<std::string, std::vector<int>>> node_sets;
  for (int a = 0; a < pd->GetNumberOfArrays(); ++a) {
    vtkDataArray* array = pd->GetArray(a);  // null for string arrays
    if (!array || !array->GetName()) continue;
    const std::string name = array->GetName();
    if (startsWith(name, kNodeSetPrefix) && name.size() > std::strlen(kNodeSetPrefix)) {
      std::vector<int> set;
      for (vtkIdType i = 0; i < n; ++i) {
        if (array->GetComponent(i, 0) != 0.0) set.push_back(static_cast<int>(i));
      }
      node_sets.emplace_back(name.substr(std::strlen(kNodeSetPrefix)), std::move(set));
    } else if (fields) {
      fields->point_data.push_back({name, arrayValues(array, nullptr)});
    }
  }
  if (fields) {
    for (int a = 0; a < cd->GetNumberOfArrays(); ++a) {
      vtkDataArray* array = cd->GetArray(a);
      if (!array || !array->GetName() || array->GetName() == label_name) continue;
      fields->cell_data.push_back({array->GetName(), arrayValues(array, &tet_cells)});
    }
  }

  TetMesh mesh = mesh_io_detail::makeMesh(path, std::move(nodes), std::move(tets), std::move(labels));
  for (auto& [name, set] : node_sets) mesh_io_detail::addNodeSet(path, mesh, name, std::move(set));
  return mesh;
}

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
  checkFileReadable(path);
  vtkNew<ErrorCollector> errors;
  vtkUnstructuredGrid* grid = nullptr;
  vtkSmartPointer<vtkAlgorithm> keep;
  if (format == MeshFileFormat::kVtu) {
    auto reader = vtkSmartPointer<vtkXMLUnstructuredGridReader>::New();
    if (!reader->CanReadFile(path.c_str())) {
      throw std::runtime_error(path + ": not a VTK XML unstructured grid (expected <VTKFile type=\"UnstructuredGrid\">)");
    }
    reader->AddObserver(vtkCommand::ErrorEvent, errors);
    reader->SetFileName(path.c_str());
    reader->Update();
    if (reader->GetErrorCode() != 0 && errors->errors.empty()) errors->errors = "VTK error code " + std::to_string(reader->GetErrorCode());
    grid = reader->GetOutput();
    keep = reader;
  } else {
    auto reader = vtkSmartPointer<vtkUnstructuredGridReader>::New();
    reader->AddObserver(vtkCommand::ErrorEvent, errors);
    reader->SetFileName(path.c_str());
    if (!reader->IsFileUnstructuredGrid()) {
      throw std::runtime_error(path + ": not a legacy VTK unstructured grid (expected 'DATASET UNSTRUCTURED_GRID')" +
                               (errors->errors.empty() ? std::string() : ": " + errors->errors));
    }
    // Legacy files may hold several SCALARS/VECTORS sections; by default VTK keeps only the first.
    reader->ReadAllScalarsOn();
    reader->ReadAllVectorsOn();
    reader->ReadAllFieldsOn();
    reader->ReadAllNormalsOn();
    reader->ReadAllTensorsOn();
    reader->ReadAllColorScalarsOn();
    reader->ReadAllTCoordsOn();
    reader->Update();
    grid = reader->GetOutput();
    keep = reader;
  }
  if (!errors->errors.empty()) throw std::runtime_error(path + ": VTK could not read the file: " + errors->errors);
  if (!grid) throw std::runtime_error(path + ": VTK returned no unstructured grid");
  return gridToMesh(path, grid, length_unit_m, fields);
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
