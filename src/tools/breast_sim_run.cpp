// breast_sim_model: builds the simulation model of a case (the software phantom or a label image) and
// writes it for ParaView / 3D Slicer / CalculiX, with the lesions and a summary.
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>

#include <nlohmann/json.hpp>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"

namespace fs = std::filesystem;
using namespace breast_sim::core;

namespace {

const char* kUsage = R"(usage: breast_sim_model --case CASE.yaml --out DIR [--target-elements N] [--json FILE]

Builds the tetrahedral simulation model of a case and writes to DIR:
  model.vtu           mesh with region labels, node sets and element quality (ParaView, 3D Slicer)
  model.inp           the same mesh for CalculiX / Abaqus (C3D4, mm)
  lesions.csv/.json   lesion positions in the prone image [mm]
  model_summary.json  counts, timings, quality, volumes
  prone_labels.nrrd, prone_surface.obj, supine_target.obj   (phantom cases only)
Options:
  --case FILE            YAML case file (see config/phantom_default.yaml)
  --out DIR              output folder (created)
  --target-elements N    overrides meshing.target_elements of the case
  --json FILE            also write the summary to FILE
)";

struct Args {
  std::string case_file, out_dir, json;
  int target_elements = 0;
};

Args parse(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw std::invalid_argument("option " + k + " needs a value\n" + kUsage);
      return argv[++i];
    };
    if (k == "--case") a.case_file = value();
    else if (k == "--out") a.out_dir = value();
    else if (k == "--json") a.json = value();
    else if (k == "--target-elements") {
      const std::string v = value();
      try {
        a.target_elements = std::stoi(v);
      } catch (...) {
        throw std::invalid_argument("--target-elements '" + v + "' is not a whole number");
      }
      if (a.target_elements <= 0) throw std::invalid_argument("--target-elements must be positive, got " + v);
    } else if (k == "-h" || k == "--help") {
      std::cout << kUsage;
      std::exit(0);
    } else throw std::invalid_argument("unknown option '" + k + "'\n" + kUsage);
  }
  if (a.case_file.empty() || a.out_dir.empty()) throw std::invalid_argument(std::string("--case and --out are required\n") + kUsage);
  return a;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const Args args = parse(argc, argv);
    const auto t0 = std::chrono::steady_clock::now();
    ModelCase c = loadModelCase(args.case_file);
    if (args.target_elements > 0) c.meshing.target_elements = args.target_elements;
    const double t_case = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const SimulationModel m = buildSimulationModel(c);
    const double t_total = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

    fs::create_directories(args.out_dir);
    const fs::path out(args.out_dir);
    // Element quality as cell data, next to the region labels the writer adds.
    MeshFields fields;
    Eigen::MatrixXd aspect(m.mesh.numTets(), 1), dihedral(m.mesh.numTets(), 1), volume(m.mesh.numTets(), 1);
    for (int t = 0; t < m.mesh.numTets(); ++t) {
      const auto& x = m.mesh.nodes();
      const auto& T = m.mesh.tets();
      const TetQuality q = tetQuality(x.row(T(t, 0)), x.row(T(t, 1)), x.row(T(t, 2)), x.row(T(t, 3)));
      aspect(t, 0) = q.aspect_ratio;
      dihedral(t, 0) = q.min_dihedral_deg;
      volume(t, 0) = q.volume_m3 * 1e9;
    }
    fields.cell_data.push_back({"aspect_ratio", aspect});
    fields.cell_data.push_back({"min_dihedral_deg", dihedral});
    fields.cell_data.push_back({"volume_mm3", volume});
    writeTetMesh((out / "model.vtu").string(), m.mesh, fields);
    writeTetMesh((out / "model.inp").string(), m.mesh, {}, 1e-3);

    nlohmann::json lesions = nlohmann::json::array();
    std::ofstream csv(out / "lesions.csv");
    csv << "name,x_mm,y_mm,z_mm,radius_mm,tet,outside_mm\n";
    for (size_t i = 0; i < m.lesions.size(); ++i) {
      const auto& l = m.lesions[i];
      const auto& e = m.lesion_embedding.points()[i];
      csv << l.name << ',' << l.position_m.x() * 1e3 << ',' << l.position_m.y() * 1e3 << ','
          << l.position_m.z() * 1e3 << ',' << l.radius_m * 1e3 << ',' << e.tet << ','
          << e.outside_distance_m * 1e3 << '\n';
      lesions.push_back({{"name", l.name},
                         {"prone_mm", {l.position_m.x() * 1e3, l.position_m.y() * 1e3, l.position_m.z() * 1e3}},
                         {"radius_mm", l.radius_m * 1e3},
                         {"tet", e.tet}});
    }
    std::ofstream(out / "lesions.json") << lesions.dump(2) << '\n';

    const double mesh_volume = m.mesh.volume();
    nlohmann::json s;
    s["case"] = c.name;
    s["elements"] = m.mesh.numTets();
    s["nodes"] = m.mesh.numNodes();
    s["node_sets"] = nlohmann::json::object();
    for (const auto& kv : m.mesh.nodeSets()) s["node_sets"][kv.first] = kv.second.size();
    s["boundary_faces"] = m.mesh.boundary().triangles.rows();
    s["prone_gravity_direction"] = {c.prone_gravity_direction.x(), c.prone_gravity_direction.y(), c.prone_gravity_direction.z()};
    s["boundary_closed"] = isClosedManifold(m.mesh.boundary().triangles);
    s["seconds"] = {{"case_and_image", t_case}, {"meshing", m.meshing.seconds}, {"total", t_total}};
    s["meshing"] = {{"passes", m.meshing.passes},
                    {"interior_size_mm", m.meshing.interior_size_m * 1e3},
                    {"skin_size_mm", m.meshing.skin_size_m * 1e3},
                    {"facet_distance_mm", m.meshing.facet_distance_m * 1e3},
                    {"chest_wall_faces", m.meshing.num_chest_wall_faces},
                    {"undecided_faces", m.meshing.num_undecided_faces},
                    {"components", m.meshing.num_components},
                    {"dropped_islands", m.meshing.dropped_components},
                    {"dropped_island_volume_mm3", m.meshing.dropped_volume_m3 * 1e9},
                    {"skin_faces", m.meshing.num_skin_faces}};
    s["quality"] = {{"inverted", m.quality.num_inverted},
                    {"min_dihedral_deg", m.quality.min_dihedral_deg},
                    {"mean_min_dihedral_deg", m.quality.mean_min_dihedral_deg},
                    {"max_aspect_ratio", m.quality.max_aspect_ratio},
                    {"mean_aspect_ratio", m.quality.mean_aspect_ratio},
                    {"dihedral_below_10deg", m.quality.num_dihedral_below_10deg}};
    s["volume_cm3"] = {{"mesh", mesh_volume * 1e6}, {"voxels", m.meshing.voxel_volume_m3 * 1e6}};
    if (c.phantom) {
      s["volume_cm3"]["analytic"] = c.phantom->prone_volume_m3 * 1e6;
      s["volume_cm3"]["supine_target_analytic"] = c.phantom->supine_volume_m3 * 1e6;
      writeLabelImage((out / "prone_labels.nrrd").string(), c.phantom->labels);
      writePhantomSurface((out / "prone_surface.obj").string(), c.phantom->prone_surface);
      writePhantomSurface((out / "supine_target.obj").string(), c.phantom->supine_surface);
    }
    s["lesions"] = lesions;
    std::ofstream(out / "model_summary.json") << s.dump(2) << '\n';
    if (!args.json.empty()) std::ofstream(args.json) << s.dump(2) << '\n';

    std::printf("breast_sim model of case '%s'\n", c.name.c_str());
    std::printf("  %-28s %d tetrahedra, %d nodes (%s boundary)\n", "mesh", m.mesh.numTets(), m.mesh.numNodes(),
                s["boundary_closed"].get<bool>() ? "closed" : "OPEN");
    std::printf("  %-28s chest wall %zu, skin %zu nodes\n", "node sets",
                m.mesh.nodeSet(node_sets::kChestWall).size(), m.mesh.nodeSet(node_sets::kSkin).size());
    std::printf("  %-28s %.1f cm3 (voxels %.1f", "volume", mesh_volume * 1e6, m.meshing.voxel_volume_m3 * 1e6);
    if (c.phantom) std::printf(", analytic %.1f, error %+.2f%%", c.phantom->prone_volume_m3 * 1e6,
                               100.0 * (mesh_volume / c.phantom->prone_volume_m3 - 1.0));
    std::printf(")\n");
    std::printf("  %-28s %d inverted, min dihedral %.1f deg, max aspect ratio %.2f\n", "quality",
                m.quality.num_inverted, m.quality.min_dihedral_deg, m.quality.max_aspect_ratio);
    std::printf("  %-28s %.2f s (meshing %.2f s in %d pass(es))\n", "time", t_total, m.meshing.seconds, m.meshing.passes);
    for (size_t i = 0; i < m.lesions.size(); ++i)
      std::printf("  lesion %-21s (%.1f, %.1f, %.1f) mm\n", m.lesions[i].name.c_str(), m.lesions[i].position_m.x() * 1e3,
                  m.lesions[i].position_m.y() * 1e3, m.lesions[i].position_m.z() * 1e3);
    std::printf("  %-28s %s\n", "written to", fs::absolute(out).string().c_str());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "breast_sim_model: error: %s\n", e.what());
    return 2;
  }
}
