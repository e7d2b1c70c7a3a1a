// Writes the seed corpus of every fuzz target into OUT/<target>/: small files from the test data
// (the VICTRE label phantom, the Gmsh dome, the case files in config/ and test/data/) and from the
// core's own writers, each format in its variants (encodings, byte orders, versions, detached data).
// Multi-file inputs are joined with fuzz_files.h's marker.
//
// Usage: fuzz_seeds OUT

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <regex>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "breast_sim/core/image/image_io_detail.h"
#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/box_mesh.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/mri/mri_volume.h"
#include "breast_sim/core/pipeline/state_file.h"
#include "fuzz_files.h"
#include "../test/core/dicom_test_files.h"

namespace {

namespace fs = std::filesystem;
using namespace breast_sim::core;
using breast_sim::fuzz::joinParts;

const std::string kSource = BREAST_SIM_SOURCE_DIR;
const std::string kSharedVictre = "/work/shared/data/victre-phantom/breast_labels_0p5mm.nrrd";

std::string readFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error("cannot read " + path);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

class Corpus {
 public:
  Corpus(fs::path out, fs::path scratch) : out_(std::move(out)), scratch_(std::move(scratch)) {}

  void add(const std::string& target, const std::string& name, const std::string& bytes) {
    const fs::path dir = out_ / target;
    fs::create_directories(dir);
    std::ofstream(dir / name, std::ios::binary) << bytes;
    ++count_[target];
  }
  /// A scratch path for a writer's output.
  std::string scratch(const std::string& name) const { return (scratch_ / name).string(); }
  const std::map<std::string, int>& counts() const { return count_; }

 private:
  fs::path out_;
  fs::path scratch_;
  std::map<std::string, int> count_;
};

std::string replaceAll(std::string s, const std::string& from, const std::string& to) {
  for (std::size_t at = s.find(from); at != std::string::npos; at = s.find(from, at + to.size()))
    s.replace(at, from.size(), to);
  return s;
}

// ---- label images ---------------------------------------------------------------------------------

LabelImage crop(const LabelImage& image, const Eigen::Vector3i& size) {
  const Eigen::Vector3i start = (image.size - size) / 2;
  LabelImage out(size, image.spacing_m, image.indexToPhysical(start.cast<double>()));
  out.direction = image.direction;
  for (int k = 0; k < size.z(); ++k)
    for (int j = 0; j < size.y(); ++j)
      for (int i = 0; i < size.x(); ++i) out.at(i, j, k) = image.at(start.x() + i, start.y() + j, start.z() + k);
  return out;
}

void imageSeeds(Corpus& c, const std::string& tag, const LabelImage& image) {
  for (const char* ext : {".nrrd", ".mha", ".nii", ".nii.gz"}) {
    const std::string p = c.scratch(tag + ext);
    writeLabelImage(p, image);
    const std::string target = std::string(ext) == ".nrrd" ? "fuzz_nrrd" : std::string(ext) == ".mha" ? "fuzz_metaimage" : "fuzz_nifti";
    c.add(target, tag + ext, readFile(p));
    c.add("fuzz_mri_" + target.substr(5), tag + ext, readFile(p));  // the MRI reader takes label images too
  }
  // Detached data, renamed to the target's second file.
  writeLabelImage(c.scratch(tag + ".nhdr"), image);
  c.add("fuzz_nrrd", tag + ".nhdr",
        joinParts({replaceAll(readFile(c.scratch(tag + ".nhdr")), tag + ".raw.gz", "data"),
                   readFile(c.scratch(tag + ".raw.gz"))}));
  writeLabelImage(c.scratch(tag + ".mhd"), image);
  c.add("fuzz_metaimage", tag + ".mhd",
        joinParts({replaceAll(readFile(c.scratch(tag + ".mhd")), tag + ".zraw", "data"),
                   readFile(c.scratch(tag + ".zraw"))}));
}

std::string rawBytes(const LabelImage& image, int bytes, bool big_endian) {
  std::string out;
  for (std::uint16_t v : image.labels) {
    for (int b = 0; b < bytes; ++b) {
      const int shift = 8 * (big_endian ? bytes - 1 - b : b);
      out += static_cast<char>(shift < 16 ? (v >> shift) & 0xff : 0);
    }
  }
  return out;
}

std::string asciiValues(const LabelImage& image) {
  std::string out;
  for (std::size_t v = 0; v < image.labels.size(); ++v) out += std::to_string(image.labels[v]) + (v % 7 == 6 ? "\n" : " ");
  return out;
}

void handMadeImageSeeds(Corpus& c, const LabelImage& image) {
  const std::string sizes = std::to_string(image.size.x()) + " " + std::to_string(image.size.y()) + " " +
                            std::to_string(image.size.z());
  const std::string head = "NRRD0004\ndimension: 3\nsizes: " + sizes + "\n";
  c.add("fuzz_nrrd", "raw_uint16_le.nrrd",
        head + "type: uint16\nendian: little\nencoding: raw\nspace: right-anterior-superior\n"
               "space directions: (0.5,0,0) (0,0.5,0) (0,0,2)\nspace origin: (10,-20,3.5)\nspace units: \"mm\" \"mm\" \"mm\"\n\n" +
            rawBytes(image, 2, false));
  c.add("fuzz_nrrd", "raw_int16_be_byteskip.nrrd",
        head + "type: short\nendian: big\nencoding: raw\nspacings: 1 1 1\nbyte skip: -1\n# comment\nkey:=value\n\n" +
            std::string(5, 'x') + rawBytes(image, 2, true));
  c.add("fuzz_nrrd", "ascii.nrrd",
        head + "type: uchar\nencoding: ascii\nspace: left-posterior-superior\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n\n" +
            asciiValues(image));
  c.add("fuzz_nrrd", "detached_raw.nhdr",
        joinParts({head + "type: uint32\nendian: little\nencoding: raw\nline skip: 1\ndata file: data\n",
                   "skipped line\n" + rawBytes(image, 4, false)}));
  const std::string mha = "ObjectType = Image\nNDims = 3\nDimSize = " + sizes +
                          "\nElementSpacing = 0.5 0.5 2\nOffset = 1 2 3\nTransformMatrix = 1 0 0 0 1 0 0 0 1\n";
  c.add("fuzz_metaimage", "raw_ushort.mha",
        mha + "BinaryData = True\nBinaryDataByteOrderMSB = False\nElementType = MET_USHORT\nElementDataFile = LOCAL\n" +
            rawBytes(image, 2, false));
  c.add("fuzz_metaimage", "msb_int.mha",
        mha + "BinaryDataByteOrderMSB = True\nElementType = MET_INT\nElementDataFile = LOCAL\n" + rawBytes(image, 4, true));
  c.add("fuzz_metaimage", "ascii.mha",
        mha + "BinaryData = False\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n" + asciiValues(image));
  c.add("fuzz_metaimage", "headersize.mhd",
        joinParts({mha + "ElementType = MET_UCHAR\nHeaderSize = -1\nElementDataFile = data\n",
                   "header" + rawBytes(image, 1, false)}));
  // NIfTI: the writer's file with the qform, then the sform, then neither.
  writeLabelImage(c.scratch("geometry.nii"), image);
  std::string nii = readFile(c.scratch("geometry.nii"));
  const auto setShort = [](std::string& b, std::size_t at, std::int16_t v) { std::memcpy(&b[at], &v, 2); };
  std::string sform_only = nii;
  setShort(sform_only, 252, 0);
  c.add("fuzz_nifti", "sform_only.nii", sform_only);
  std::string no_orientation = sform_only;
  setShort(no_orientation, 254, 0);
  c.add("fuzz_nifti", "method1.nii", no_orientation);
}

// ---- MRI volumes (readMriVolume) ------------------------------------------------------------------

/// Float volumes as writeMriVolume writes them in every format, and DICOM series of four slices as
/// writeDicomSeries writes them: whole, with a slice missing, and on an oblique grid.
void mriSeeds(Corpus& c) {
  ScalarImage image;
  image.geometry.size = Eigen::Vector3i(6, 5, 4);
  image.geometry.spacing_m = Eigen::Vector3d(0.8e-3, 0.9e-3, 1.5e-3);
  image.geometry.origin_m = Eigen::Vector3d(-12e-3, 30e-3, -7e-3);
  image.values.resize(static_cast<std::size_t>(image.geometry.numVoxels()));
  for (std::size_t v = 0; v < image.values.size(); ++v) image.values[v] = static_cast<float>((v * 37) % 900) + 0.25f;
  for (const char* ext : {".nii", ".nii.gz", ".nrrd", ".mha"}) {
    const std::string p = c.scratch(std::string("mri") + ext);
    writeMriVolume(p, image);
    const std::string e = ext;
    const std::string target = e == ".nrrd" ? "fuzz_mri_nrrd" : e == ".mha" ? "fuzz_mri_metaimage" : "fuzz_mri_nifti";
    c.add(target, "float" + e, readFile(p));
  }
  ScalarImage oblique = image;
  const double a = 0.3;
  oblique.geometry.direction << std::cos(a), 0, std::sin(a), 0, 1, 0, -std::sin(a), 0, std::cos(a);
  for (const auto& [tag, volume] : {std::pair<std::string, const ScalarImage*>{"axial", &image}, {"oblique", &oblique}}) {
    const fs::path folder = c.scratch("dicom_" + tag);
    writeDicomSeries(folder.string(), *volume);
    std::vector<std::string> slices;
    for (int k = 1; k <= 4; ++k) slices.push_back(readFile((folder / ("IM0000" + std::to_string(k) + ".dcm")).string()));
    c.add("fuzz_mri_dicom", tag + "_4_slices", joinParts(slices));
    c.add("fuzz_mri_dicom", tag + "_slice_3_missing", joinParts({slices[0], slices[1], "", slices[3]}));
  }
  // Hand-made series in the encodings GDCM does not write: explicit VR little and big endian, 8 and
  // 12 bits, sequences of defined and undefined length (items of both kinds, a UN sequence) in front
  // of a slice's attributes, and encapsulated (JPEG) pixel data.
  namespace dicom = breast_sim::test::dicom;
  const auto series = [](dicom::Slice s, int count) {
    std::vector<std::string> files;
    for (int k = 0; k < count; ++k, s.z_mm += 1.5) files.push_back(dicom::slice(s));
    return files;
  };
  dicom::Slice explicit_bytes;
  explicit_bytes.explicit_vr = true;
  explicit_bytes.bits = explicit_bytes.stored = 8;
  explicit_bytes.high = 7;
  c.add("fuzz_mri_dicom", "explicit_8_bits", joinParts(series(explicit_bytes, 3)));
  dicom::Slice big;
  big.explicit_vr = big.big = true;
  big.stored = 12;
  big.high = 15;
  big.sign = 1;
  big.slope = "2";
  c.add("fuzz_mri_dicom", "big_endian_12_bits", joinParts(series(big, 4)));
  dicom::Bytes item(true);
  item.element(0x0008, 0x1150, "UI", dicom::uid("1.2.840.10008.5.1.4.1.1.4"));
  dicom::Bytes nested;
  nested.element(0x0008, 0x0100, "SH", "CODE01");
  dicom::Bytes sequences(true);
  sequences.head(0x0008, 0x1140, "SQ", dicom::kUndefined)
      .head(0xFFFE, 0xE000, "", dicom::kUndefined).raw(item.str()).head(0xFFFE, 0xE00D, "", 0)
      .head(0xFFFE, 0xE000, "", static_cast<std::uint32_t>(item.str().size())).raw(item.str())
      .head(0xFFFE, 0xE0DD, "", 0)
      .head(0x0008, 0x1250, "SQ", static_cast<std::uint32_t>(8 + item.str().size()))
      .head(0xFFFE, 0xE000, "", static_cast<std::uint32_t>(item.str().size())).raw(item.str())
      .head(0x0009, 0x1010, "UN", dicom::kUndefined)
      .head(0xFFFE, 0xE000, "", static_cast<std::uint32_t>(nested.str().size())).raw(nested.str())
      .head(0xFFFE, 0xE0DD, "", 0);
  dicom::Slice plain;
  plain.explicit_vr = true;
  std::vector<std::string> with_sequences;
  for (int k = 0; k < 3; ++k, plain.z_mm += 1.5) with_sequences.push_back(dicom::part10(dicom::kExplicit, sequences.str() + dicom::sliceDataSet(plain)));
  c.add("fuzz_mri_dicom", "sequences", joinParts(with_sequences));
  dicom::Bytes jpeg(true);
  jpeg.element(0x0020, 0x000E, "UI", dicom::uid("1.2.3.4"))
      .head(0x7FE0, 0x0010, "OB", dicom::kUndefined).head(0xFFFE, 0xE000, "", 0)
      .head(0xFFFE, 0xE000, "", 4).raw(std::string("\xFF\xD8\xFF\xD9", 4)).head(0xFFFE, 0xE0DD, "", 0);
  c.add("fuzz_mri_dicom", "jpeg", dicom::part10(dicom::kJpeg, jpeg.str()));
}

// ---- meshes ---------------------------------------------------------------------------------------

TetMesh smallMesh() {
  TetMesh box = makeBoxMesh(Eigen::Vector3i(2, 1, 1), Eigen::Vector3d(0.04, 0.02, 0.02));
  std::vector<int> labels(static_cast<std::size_t>(box.numTets()));
  for (int t = 0; t < box.numTets(); ++t) labels[t] = t % 2 == 0 ? 1 : 2;
  TetMesh mesh(box.nodes(), box.tets(), labels);
  mesh.setNodeSet("chest_wall", box.nodeSet("y_min"));
  mesh.setNodeSet("skin", box.nodeSet("y_max"));
  return mesh;
}

void meshSeeds(Corpus& c) {
  const TetMesh mesh = smallMesh();
  MeshFields fields;
  Eigen::MatrixXd displacement = mesh.nodes() * 0.1;
  fields.point_data.push_back({"displacement_mm", displacement, true});
  fields.cell_data.push_back({"von_mises_pa", Eigen::VectorXd::LinSpaced(mesh.numTets(), 1.0, 9.0), false});
  for (const bool binary : {false, true}) {
    for (const auto version : {GmshVersion::kMsh22, GmshVersion::kMsh41}) {
      MeshWriteOptions o;
      o.gmsh.version = version;
      o.gmsh.binary = binary;
      const std::string name = std::string(version == GmshVersion::kMsh22 ? "v22" : "v41") + (binary ? "_binary" : "_ascii") + ".msh";
      writeTetMesh(c.scratch(name), mesh, {}, 1e-3, o);
      c.add("fuzz_gmsh", name, readFile(c.scratch(name)));
    }
    MeshWriteOptions o;
    o.vtk.binary = binary;
    const std::string suffix = binary ? "_binary" : "_ascii";
    writeTetMesh(c.scratch("mesh" + suffix + ".vtk"), mesh, fields, 1e-3, o);
    c.add("fuzz_vtk_legacy", "writer" + suffix + ".vtk", readFile(c.scratch("mesh" + suffix + ".vtk")));
    writeTetMesh(c.scratch("mesh" + suffix + ".vtu"), mesh, fields, 1e-3, o);
    c.add("fuzz_vtu", "writer" + suffix + ".vtu", readFile(c.scratch("mesh" + suffix + ".vtu")));
  }
  writeTetMesh(c.scratch("mesh.node"), mesh, {}, 1e-3);
  c.add("fuzz_tetgen", "writer", joinParts({readFile(c.scratch("mesh.node")), readFile(c.scratch("mesh.ele"))}));
  c.add("fuzz_tetgen", "attributes_markers",
        joinParts({"# nodes\n5 3 1 1\n0 0 0 0 7 1\n1 10 0 0 7 1\n2 0 10 0 7 0\n3 0 0 10 7 1\n4 10 10 10 7 0\n",
                   "2 4 1  # tets\n0 0 1 2 3 1.0e+00\n1 1 2 3 4 2\n"}));
  writeTetMesh(c.scratch("mesh.inp"), mesh, {}, 1e-3);
  c.add("fuzz_inp", "writer.inp", readFile(c.scratch("mesh.inp")));
  c.add("fuzz_inp", "sets.inp",
        "** hand-made\n*HEADING\nsets\n*NODE, NSET=ALLNODES\n1, 0, 0, 0\n2, 10., 0., 0.\n3, 0, 10, 0\n4, 0, 0, 10\n"
        "5, 10, 10, 10\n*ELEMENT, TYPE=C3D4, ELSET=FAT\n1, 1, 2, 3,\n4\n*ELEMENT, TYPE=S3, ELSET=SKIN_SHELL\n9, 1, 2, 3\n"
        "*ELEMENT, TYPE=C3D4\n2, 2, 3, 4, 5\n*ELSET, ELSET=REGION_2\n2\n*ELSET, ELSET=ALL, GENERATE\n1, 2, 1\n"
        "*NSET, NSET=WALL\n1, 2, 3\n*NSET, NSET=SKIN, GENERATE\n2, 5, 3\n*NSET, NSET=BOTH\nWALL, SKIN, 4\n"
        "*MATERIAL, NAME=TISSUE\n*ELASTIC\n3000., 0.49\n");

  // Every writer variant of VTK itself (test/data/vtk_variants).
  for (const auto& entry : fs::directory_iterator(kSource + "/test/data/vtk_variants")) {
    const std::string ext = entry.path().extension().string();
    if (ext == ".vtk" || ext == ".vtu") {
      c.add(ext == ".vtk" ? "fuzz_vtk_legacy" : "fuzz_vtu", entry.path().filename().string(), readFile(entry.path().string()));
    }
  }
  // Legacy VTK 5.1 (offsets and connectivity), as VTK 9 writes by default.
  c.add("fuzz_vtk_legacy", "v51_ascii.vtk",
        "# vtk DataFile Version 5.1\nhand-made\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 5 float\n"
        "0 0 0 10 0 0 0 10 0\n0 0 10 10 10 10\n\nCELLS 4 9\nOFFSETS vtktypeint64\n0 4 8 9\n"
        "CONNECTIVITY vtktypeint64\n0 1 2 3 1 2 3 4 4\n\nCELL_TYPES 3\n10\n10\n1\n\n"
        "CELL_DATA 3\nSCALARS region int 1\nLOOKUP_TABLE default\n1 2 0\n"
        "POINT_DATA 5\nSCALARS nodeset_chest_wall unsigned_char\nLOOKUP_TABLE default\n1 1 1 0 0\n"
        "VECTORS displacement_mm double\n0 0 0 1 1 1 0 0 0 1 1 1 0 0 0\n"
        "FIELD FieldData 1\nmarker 2 5 float\n0 1 2 3 4 5 6 7 8 9\nMETADATA\nINFORMATION 0\n\n");

  // The Gmsh dome's header (physical names) with a few of its elements and their nodes.
  const std::string dome = readFile(kSource + "/test/data/dome_breast.msh");
  const std::size_t nodes_at = dome.find("$Nodes\n"), elements_at = dome.find("$Elements\n");
  if (nodes_at != std::string::npos && elements_at != std::string::npos) {
    std::istringstream elements(dome.substr(elements_at + 10));
    std::string line;
    std::getline(elements, line);  // count
    std::map<std::pair<int, int>, int> taken;  // (type, physical) → elements kept
    std::vector<std::string> kept;
    std::set<long> used;
    while (std::getline(elements, line) && line != "$EndElements") {
      std::istringstream l(line);
      long number = 0, type = 0, ntags = 0;
      l >> number >> type >> ntags;
      std::vector<long> values;
      for (long v = 0; l >> v;) values.push_back(v);
      if (ntags < 1 || values.size() <= static_cast<std::size_t>(ntags)) continue;
      if (taken[{static_cast<int>(type), static_cast<int>(values[0])}]++ >= 3) continue;
      kept.push_back(line);
      for (std::size_t k = static_cast<std::size_t>(ntags); k < values.size(); ++k) used.insert(values[k]);
    }
    std::istringstream nodes(dome.substr(nodes_at + 7));
    std::getline(nodes, line);
    std::vector<std::string> node_lines;
    while (std::getline(nodes, line) && line != "$EndNodes") {
      if (used.count(std::atol(line.c_str()))) node_lines.push_back(line);
    }
    std::string out = dome.substr(0, nodes_at) + "$Nodes\n" + std::to_string(node_lines.size()) + "\n";
    for (const auto& n : node_lines) out += n + "\n";
    out += "$EndNodes\n$Elements\n" + std::to_string(kept.size()) + "\n";
    for (const auto& e : kept) out += e + "\n";
    c.add("fuzz_gmsh", "dome_excerpt.msh", out + "$EndElements\n");
  }
  c.add("fuzz_gmsh", "v41_entities.msh",
        "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$PhysicalNames\n2\n2 11 \"chest_wall\"\n3 1 \"fat\"\n$EndPhysicalNames\n"
        "$Entities\n0 0 1 1\n5 0 0 0 10 10 0 1 11 0\n7 0 0 0 10 10 10 1 1 1 5\n$EndEntities\n"
        "$Nodes\n2 5 1 5\n2 5 0 3\n1\n2\n3\n0 0 0\n10 0 0\n0 10 0\n3 7 0 2\n4\n5\n0 0 10\n10 10 10\n$EndNodes\n"
        "$Elements\n2 3 1 3\n2 5 2 1\n1 1 2 3\n3 7 4 2\n2 1 2 3 4\n3 2 3 4 5\n$EndElements\n"
        "$Comments\nskipped\n$EndComments\n");
}

// ---- state files ----------------------------------------------------------------------------------

void stateSeeds(Corpus& c) {
  StateFile f;
  f.nodes = 5;
  f.tets = 2;
  f.mesh_fingerprint = 123456789.0;
  PipelineState& s = f.state;
  s.simulation.displacement_m = Eigen::VectorXd::LinSpaced(15, -1e-3, 1e-3);
  s.simulation.velocity_mps = Eigen::VectorXd::Constant(15, 1e-4);
  s.simulation.time_s = 2.5;
  s.simulation.step = 12;
  s.modulus_factors = Eigen::VectorXd::Constant(2, 1.5);
  s.alpha.alpha_per_pa = 1e-4;
  s.alpha.phase = AlphaController::Phase::kSettling;
  s.alpha.rate = 0.5;
  s.alpha.oscillations = 1;
  s.alpha.runs[0] = -1;
  s.alpha.runs[1] = 1;
  s.stage = PipelineStage::kSliding;
  s.sliding_targets_m = Points::Constant(2, 3, 0.01);
  s.sliding_slip_directions = Points::Zero(2, 3);
  s.morphing_forces_n = Points::Constant(1, 3, 0.2);
  s.gravity_load_mps2 = Eigen::Vector3d(0, 9.81, 9.81);
  f.has_gravity_load = f.has_rest_shape = true;
  f.rest_m = Points::Random(5, 3);
  s.element_alpha_per_pa = Eigen::Vector2d(0.0, 2e-3);
  writeStateFile(c.scratch("state.bin"), f);
  readStateFile(c.scratch("state.bin"));
  const std::string full = readFile(c.scratch("state.bin"));
  c.add("fuzz_state", "full.bin", full);
  // Files of earlier versions end after the rest shape, the gravity load, the slip directions, the
  // morphing forces. Each must read: a seed the reader refuses would test only its first check.
  const std::size_t alpha = 8 + 2 * 8, rest = 8 + 15 * 8, gravity = 8 + 3 * 8, slip = 8 + 6 * 8;
  const std::pair<const char*, std::size_t> earlier[] = {{"without_alpha.bin", alpha},
                                                         {"without_rest.bin", alpha + rest},
                                                         {"without_gravity.bin", alpha + rest + gravity},
                                                         {"without_slip.bin", alpha + rest + gravity + slip}};
  for (const auto& [name, cut] : earlier) {
    const std::string bytes = full.substr(0, full.size() - cut);
    std::ofstream(c.scratch(name), std::ios::binary) << bytes;
    readStateFile(c.scratch(name));  // throws, and the seed run fails
    c.add("fuzz_state", name, bytes);
  }
}

// ---- case files -----------------------------------------------------------------------------------

/// A case file with its chain of bases as parts case.yaml, b1.yaml, …; image and mesh paths point at
/// the fuzz target's own image.nrrd and mesh.vtu.
void caseSeed(Corpus& c, const fs::path& file) {
  std::vector<std::string> parts;
  fs::path current = file;
  static const std::regex base(R"((^|\n)base:[^\n]*)");
  static const std::regex image_path(R"(path:\s*[^\n,}]*\.nrrd)");
  static const std::regex mesh_path(R"(path:\s*[^\n,}]*\.(msh|vtu|vtk|inp|node|ele))");
  for (int depth = 0; depth < 4 && fs::exists(current); ++depth) {
    std::string text = readFile(current.string());
    std::smatch m;
    fs::path next;
    if (std::regex_search(text, m, base)) {
      std::string name = m.str(0).substr(m.str(0).find("base:") + 5);
      name = name.substr(0, name.find('#'));
      name.erase(0, name.find_first_not_of(" \t"));
      name.erase(name.find_last_not_of(" \t\r") + 1);
      next = current.parent_path() / name;
      text = std::regex_replace(text, base, "$1base: b" + std::to_string(depth + 1) + ".yaml");
    }
    text = std::regex_replace(text, image_path, "path: image.nrrd");
    text = std::regex_replace(text, mesh_path, "path: mesh.vtu");
    text = replaceAll(text, "units: mm", "units: m");
    text = replaceAll(text, "chest_wall: chest_wall", "chest_wall: y_min");
    text = replaceAll(text, "skin: skin", "skin: y_max");
    parts.push_back(text);
    if (next.empty()) break;
    current = next;
  }
  c.add("fuzz_case", file.filename().string(), joinParts(parts));
}

void caseSeeds(Corpus& c) {
  for (const std::string& folder : {kSource + "/config", kSource + "/test/data"}) {
    for (const auto& entry : fs::directory_iterator(folder)) {
      if (entry.path().extension() == ".yaml" && entry.path().filename() != "node.yaml") caseSeed(c, entry.path());
    }
  }
  c.add("fuzz_case", "tiny_image_case.yaml",
        "image:\n  path: image.nrrd\n  labels: {fat: [1], skin: [2], chest_wall: [40]}\n  nipples_mm: [[12, 8, 4]]\n"
        "  prone_gravity_direction: [0, 1, 0]\nlesions:\n  - {name: L1, position_mm: [12, 8, 4], radius_mm: 1}\n"
        "meshing: {target_elements: 500, skin_size_factor: 0.5, perturb: false}\n");
  c.add("fuzz_case", "box_mesh_case.yaml",
        "mesh: {path: mesh.vtu, units: m, chest_wall: y_min, skin: y_max, voxel_size_mm: 2, regions: {fat: [0]}}\n");
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::cerr << "usage: fuzz_seeds OUT\n";
    return 2;
  }
  const fs::path out = argv[1];
  const fs::path scratch = out / ".scratch";
  fs::create_directories(scratch);
  try {
    Corpus c(out, scratch);
    LabelImage tiny(Eigen::Vector3i(7, 5, 3), Eigen::Vector3d(0.5e-3, 0.5e-3, 2e-3), Eigen::Vector3d(1e-3, 2e-3, 3e-3));
    for (std::size_t v = 0; v < tiny.labels.size(); ++v) tiny.labels[v] = static_cast<std::uint16_t>(v % 5);
    imageSeeds(c, "tiny_uint8", tiny);
    LabelImage wide = tiny;
    wide.labels[3] = 1000;
    imageSeeds(c, "tiny_uint16", wide);
    handMadeImageSeeds(c, wide);
    const std::string victre = kSource + "/test/data/victre_labels_1mm.nrrd";
    const LabelImage victre_crop = crop(readLabelImage(victre), Eigen::Vector3i(8, 8, 8));
    imageSeeds(c, "victre_1mm", victre_crop);
    // The file's own header (its space, kinds and origin as the generator wrote them) over the crop.
    std::string header = readFile(victre);
    header = std::regex_replace(header.substr(0, header.find("\n\n") + 2), std::regex("sizes: [^\n]*"), "sizes: 8 8 8");
    std::string raw;
    for (std::uint16_t l : victre_crop.labels) raw += static_cast<char>(l);
    c.add("fuzz_nrrd", "victre_header.nrrd", header + image_io::deflateBytes(raw, image_io::Wrapper::kGzip));
    if (fs::exists(kSharedVictre)) imageSeeds(c, "victre_0p5mm", crop(readLabelImage(kSharedVictre), Eigen::Vector3i(8, 8, 8)));
    mriSeeds(c);
    meshSeeds(c);
    stateSeeds(c);
    caseSeeds(c);
    fs::remove_all(scratch);
    for (const auto& [target, n] : c.counts()) std::cout << target << ": " << n << " seeds\n";
  } catch (const std::exception& e) {
    std::cerr << "fuzz_seeds: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
