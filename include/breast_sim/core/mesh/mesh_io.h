#pragma once
/// @file mesh_io.h
/// Reading and writing tetrahedral meshes: Gmsh MSH 2.2 / 4.1 (ASCII and binary), VTK XML `.vtu` and
/// legacy `.vtk` unstructured grids, TetGen `.node`/`.ele`, and Abaqus / CalculiX `.inp` (C3D4).
///
/// \note Units: a file's coordinates times `length_unit_m` are metres. Readers multiply by it, writers
/// divide by it (1.0 for files in metres, 1e-3 for files in millimetres).
/// \note Orientation: tetrahedra come back positively oriented whatever their order in the file,
/// because TetMesh's constructor swaps the last two nodes of negatively oriented ones. Writers write
/// the mesh's (positive) order.
/// \note Order: nodes keep their order in the file. Tetrahedra are sorted by their element number where
/// the format numbers them (.msh, .inp, .ele), which undoes the grouping by region some writers do.
/// Nodes no tetrahedron uses (e.g. those of skipped surface elements) are kept.
/// \note Errors: a malformed file raises std::runtime_error whose message starts with the path and
/// the place, then says what is wrong: "mesh.msh:12: expected 4 node indices for element 7, got 3"
/// for text, "mesh.msh: byte 1234: …" for binary data, "mesh.vtu: …" for files read by VTK (which
/// reports no place). A file that cannot be opened or written, or that holds no 4-node tetrahedron,
/// raises std::runtime_error naming it.

#include <string>
#include <vector>

#include <Eigen/Core>

#include "breast_sim/core/mesh/tet_mesh.h"

namespace breast_sim::core {

/// A named array attached to the points or the cells of a mesh, for visualization (ParaView, Slicer).
struct MeshField {
  std::string name;
  /// #N×C for point data or #T×C for cell data; C components (1 = scalar, 3 = vector).
  Eigen::MatrixXd values;
  /// The values are lengths [m] (e.g. a displacement): writers divide them by `length_unit_m` like the
  /// coordinates, so "Warp By Vector" with scale 1 shows the deformed shape. Other values are written
  /// as they are.
  bool is_length = false;
};

/// Fields written beside a mesh. Names must be non-empty and unique within point_data and within
/// cell_data; "region" (cell) and "nodeset_*" (point) are reserved for the mesh's own data.
struct MeshFields {
  std::vector<MeshField> point_data;  ///< rows = #N
  std::vector<MeshField> cell_data;   ///< rows = #T
};

/// Mesh file formats, chosen from the extension (case-insensitive).
enum class MeshFileFormat {
  kGmsh,       ///< .msh
  kVtu,        ///< .vtu (VTK XML unstructured grid)
  kVtkLegacy,  ///< .vtk (VTK legacy unstructured grid)
  kTetGen,     ///< .node + .ele (either path)
  kAbaqusInp,  ///< .inp
};

/// @throws std::runtime_error naming the path and the supported extensions when the extension is
///         none of .msh .vtu .vtk .node .ele .inp.
MeshFileFormat meshFileFormat(const std::string& path);

enum class GmshVersion { kMsh22, kMsh41 };

/// How to write a .msh file. The default (2.2 ASCII) is the one nearly every tool reads.
struct GmshOptions {
  GmshVersion version = GmshVersion::kMsh22;
  bool binary = false;  ///< little-endian binary, as Gmsh writes on x86
};

/// How to write a .vtu / .vtk file.
struct VtkOptions {
  /// .vtu: appended raw data, zlib-compressed; .vtk: legacy binary. false writes ASCII (VTK then
  /// prints coordinates with fewer digits than a double holds).
  bool binary = true;
  /// When set (#N×3 [m]), these node positions are written instead of the rest positions: a deformed
  /// configuration (ParaView shows it as is; the rest positions are the mesh's). Must outlive the call.
  const Points* positions_m = nullptr;
};

struct MeshWriteOptions {
  GmshOptions gmsh;  ///< used for .msh only
  VtkOptions vtk;    ///< used for .vtu and .vtk only
};

// ---- by extension ---------------------------------------------------------------------------------

/// Reads a tetrahedral mesh, choosing the reader from the extension: .msh .vtu .vtk .node .ele .inp.
/// @param length_unit_m  metres per file length unit (1e-3 for a file in mm); must be > 0
/// @throws std::runtime_error for an unknown extension, an unreadable or malformed file
TetMesh readTetMesh(const std::string& path, double length_unit_m = 1.0);

/// Writes a tetrahedral mesh, choosing the writer from the extension.
/// @param fields  point and cell data; only .vtu and .vtk can hold them
/// @param length_unit_m  metres per file length unit; must be > 0
/// @throws std::invalid_argument when fields are given for a format that cannot hold them or a field
///         is malformed (naming it); std::runtime_error for an unknown extension or a failed write
void writeTetMesh(const std::string& path, const TetMesh& mesh, const MeshFields& fields = {},
                  double length_unit_m = 1.0, const MeshWriteOptions& options = {});

// ---- Gmsh -----------------------------------------------------------------------------------------

/// Reads Gmsh MSH 2.0–2.2 or 4.1, ASCII or binary (little-endian). Only 4-node tetrahedra (type 4)
/// become elements; points, lines, triangles and other types are skipped.
/// Region label of a tetrahedron: MSH 4.1: the first physical tag of its volume entity, or the
/// entity tag when the entity has none; MSH 2.x: its first tag (physical), or its second
/// (elementary) when the physical tag is 0, or 0 when it has no tags.
/// Node sets: each *named* physical group ($PhysicalNames) of dimension 0, 1 or 2 becomes a node set
/// holding the nodes of its elements. MSH 4.0 and 3.x are not supported.
TetMesh readGmsh(const std::string& path, double length_unit_m = 1.0);

/// Writes tetrahedra (type 4) with their region labels. MSH 2.2: tags (label, label); MSH 4.1: one
/// volume entity per label, whose physical tag is the label. Node sets are not written.
void writeGmsh(const std::string& path, const TetMesh& mesh, const GmshOptions& options = {},
               double length_unit_m = 1.0);

// ---- VTK ------------------------------------------------------------------------------------------

/// Reads a VTK unstructured grid: XML (.vtu) or legacy (.vtk) by extension. Both are parsed here,
/// not by VTK 9.1's readers, which size arrays from a file's claimed counts and crash on malformed
/// legacy files: every count is checked against the bytes that follow it before anything is
/// allocated. Legacy: file versions 2.0–5.1, ASCII or BINARY, every attribute and FIELD array type
/// (string arrays skipped). XML: ascii, inline base64 or appended (raw or base64) data, uncompressed
/// or zlib / LZ4 / LZMA blocks (a block may expand at most 1032 times), UInt32 or UInt64 headers,
/// either byte order, several pieces.
/// Only VTK_TETRA cells become elements; other cells are skipped (their points are kept; their point
/// ids must still be points of the file). Region labels come from the first cell array named
/// "region", "label" or "gmsh:physical" (0 if none), which must hold integers. Point arrays
/// "nodeset_<name>" become node sets (nodes with a non-zero value).
/// @param fields  if not null, receives the other point arrays and the other cell arrays (restricted
///                to the tetrahedra), as stored in the file (not scaled; is_length is false); left
///                unchanged when the file is refused
/// @throws std::runtime_error "<path>:<line>: …" (XML, legacy text), "<path>: byte <offset>: …"
///         (legacy binary) or "<path>: …" (the mesh: a point id out of range, a tetra without 4
///         points, no tetrahedra).
TetMesh readVtkUnstructured(const std::string& path, double length_unit_m = 1.0,
                            MeshFields* fields = nullptr);

/// Writes a .vtu (XML) file for ParaView and 3D Slicer: points (double), VTK_TETRA cells, cell data
/// "region" (Int32) and `fields.cell_data`, point data `fields.point_data` (Float64) and one Int32
/// 0/1 array "nodeset_<name>" per node set. Rest positions are the points; show a deformation with
/// a displacement field and "Warp By Vector".
/// @throws std::invalid_argument naming a field whose row count is not #N (point) / #T (cell), whose
///         name is empty, repeated or reserved, or that has no column
void writeVtu(const std::string& path, const TetMesh& mesh, const MeshFields& fields = {},
              double length_unit_m = 1.0, const VtkOptions& options = {});

/// Same content as writeVtu, in the legacy .vtk format (file version 4.2, which old and new VTK-based
/// tools read).
void writeVtkLegacy(const std::string& path, const TetMesh& mesh, const MeshFields& fields = {},
                    double length_unit_m = 1.0, const VtkOptions& options = {});

// ---- TetGen ---------------------------------------------------------------------------------------

/// Reads a TetGen pair `<base>.node` + `<base>.ele`; `path` may name either. Node numbers may start at
/// 0 or 1 (any numbering in fact: .ele refers to the numbers of .node). The first element attribute,
/// if any, is the region label (it must be an integer). '#' starts a comment. Only 4-node elements
/// are supported (a 10-node .ele is rejected).
TetMesh readTetGen(const std::string& path, double length_unit_m = 1.0);

/// Writes `<base>.node` (1-based, no attributes or markers) and `<base>.ele` (4 nodes, the region
/// label as the one attribute); `path` may name either file. Node sets are not written.
void writeTetGen(const std::string& path, const TetMesh& mesh, double length_unit_m = 1.0);

// ---- Abaqus / CalculiX ----------------------------------------------------------------------------

/// Reads an Abaqus / CalculiX input file: *NODE, *ELEMENT with TYPE=C3D4 (other element types'
/// data lines are skipped), *NSET (ids, names of earlier sets, or GENERATE) and *ELSET.
/// Keywords and parameters are case-insensitive; lines starting with "**" are comments; other
/// keywords are skipped with their data lines; *INCLUDE is not supported.
/// Region label from the element set: ELSET= of the C3D4 *ELEMENT block, else the first *ELSET that
/// lists the element, else 0. A set's label is the integer its name ends with ("REGION_29" → 29,
/// "EB-3" → 3, "R_-2" → −2; at most 9 digits). Names without one are numbered on from the largest
/// such integer (from 0 when none is positive) by their order of appearance among the distinct set
/// names of C3D4 *ELEMENT blocks and *ELSET keywords: with REGION_29, FAT and DEEP, FAT is 30 and
/// DEEP 31; with FAT and DEEP alone, 1 and 2. So a named set never shares a label with a numbered
/// one; numbered names ending in the same integer ("A_1", "B_1") do share it.
/// Node sets: every *NSET, and NSET= of *NODE, under its name as written.
TetMesh readAbaqusInp(const std::string& path, double length_unit_m = 1.0);

/// Writes *NODE (1-based), one "*ELEMENT, TYPE=C3D4, ELSET=REGION_<label>" block per label
/// (element number = tet index + 1), and one *NSET per node set.
void writeAbaqusInp(const std::string& path, const TetMesh& mesh, double length_unit_m = 1.0);

}  // namespace breast_sim::core
