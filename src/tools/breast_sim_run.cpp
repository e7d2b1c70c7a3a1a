// breast_sim_run: the whole prone-to-supine run of a case (the software phantom, a label image, a mesh
// or a prone MRI, segmented first): builds the simulation model and writes it for ParaView / 3D Slicer
// / CalculiX, loads it with the gravity of the supine position (stiffening, sliding), morphs it to the
// target surface (seed Figure 2), and writes the deformed meshes, a ParaView series, the lesion
// positions, metrics and cross-section images; for an MRI case also the segmentation and the
// simulated supine MRI (seed Figure 4e).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <optional>
#include <string>

#include <unistd.h>

#include <nlohmann/json.hpp>

#include "breast_sim/core/image/label_image.h"
#include "breast_sim/core/mesh/mesh_io.h"
#include "breast_sim/core/mesh/tet_quality.h"
#include "breast_sim/core/model/model_case.h"
#include "breast_sim/core/model/phantom.h"
#include "breast_sim/core/morphing/surface_morphing.h"
#include "breast_sim/core/mri/mri_case.h"
#include "breast_sim/core/mri/mri_cross_sections.h"
#include "breast_sim/core/pipeline/case_file.h"
#include "breast_sim/core/pipeline/lesion_uncertainty.h"
#include "breast_sim/core/pipeline/prone_to_supine.h"
#include "breast_sim/core/reference/model_choice.h"
#include "breast_sim/core/render/cross_section.h"
#include "segmentation_summary.h"

namespace fs = std::filesystem;
using namespace breast_sim::core;

namespace {

const char* kUsage = R"(usage: breast_sim_run --case CASE.yaml --out DIR [--target-elements N] [--model-only]
                      [--solver multigrid|aggregation|cholmod|jacobi-pcg] [--no-sliding] [--no-morphing]
                      [--coarse-elements N]
                      [--frames N] [--json FILE] [--quiet]

Builds the tetrahedral simulation model of a case (an MRI case is segmented first) and runs the
prone-to-supine pipeline on it: gravity of the supine position with von Mises stiffening and sliding
on the chest wall until it settles, then morphing to the target surface (the case's `simulation:`,
`sliding:` and `morphing:` maps, see docs/case_files.md). Writes to DIR:
  model.vtu             prone mesh with region labels, node sets and element quality (ParaView, 3D Slicer)
  model.inp             the same mesh for CalculiX / Abaqus (C3D4, mm)
  supine_gravity.vtu    after gravity (and sliding): displacement_mm, sliding_mm; von_mises_pa, modulus_factor
  supine.vtu            the final supine shape (after morphing), same fields
  series.pvd, series/   the run as a ParaView time series (a frame every N steps)
  lesions.csv/.json     lesion positions, prone, after gravity and supine [mm]; with `uncertainty:` enabled,
                        each supine position's covariance [mm^2] and confidence ellipsoid (docs/uncertainty.md)
  sliding.csv           with sliding: each chest-wall node's rest position and sliding vector after gravity
                        and at the end [mm] (scripts/plot_sliding.py draws them)
  metrics.json          steps, reversals, alpha, timings, surface distances, volume change, inverted elements
  cross_sections.png    axial / coronal / sagittal cuts: prone, after gravity, after morphing (target in red)
  model_summary.json    counts, timings, quality and volumes of the model
  case_effective.yaml   the case as it ran: every key with the value used (command-line overrides included)
  prone_labels.nrrd, prone_surface.obj, supine_target.obj   (phantom cases only)
An MRI case (mri:) also writes:
  prone_labels.nrrd     the segmentation the model is built from (on the MRI's grid; 3D Slicer)
  segmentation.png      cross-sections of the prone MRI with the segmentation outlined
  segmentation.json     volumes per class, nipples, levels, the chest wall's coverage, seconds; with
                        mri.truth the Dice per class and the chest-wall boundary's distance to the truth
  supine_mri.nii.gz, supine_mri.nrrd   the simulated supine MRI (float, the prone spacing; overlays the input)
  supine_labels.nrrd    the segmentation carried into the supine shape
  supine_mri.png        cross-sections of the prone and the simulated supine MRI, labels outlined
Options:
  --case FILE            YAML case file (docs/case_files.md)
  --out DIR              output folder (created)
  --target-elements N    overrides meshing.target_elements of the case
  --model-only           build and write the model, do not simulate
  --solver NAME          overrides simulation.solver
  --no-sliding           overrides simulation.sliding (chest wall fixed)
  --no-morphing          overrides morphing.enabled (gravity only; also turns coarse_start off)
  --coarse-elements N    overrides coarse_start.elements: gravity, sliding and most of the morphing on
                         a mesh of about N elements, the last morphing steps on the model (0 = off)
  --frames N             a series frame every N accepted steps (default 5; 0 = no series)
  --max-lesion-error-mm E  "model no more than a scene needs": mesh with the fewest elements whose
                         measured lesion error against the CalculiX reference is at most E mm (from
                         --error-curve, bench_speed_accuracy's JSON, e.g.
                         docs/speed_accuracy/sweep_supine.json); overrides the case's target_elements
  --json FILE            also write the metrics to FILE
  --quiet                no progress bar
Exit status: 0 done, 2 bad input (the message names the file, key or value), 3 a stage did not
converge or an element ended inverted (the outputs are still written).
)";

struct Args {
  std::string case_file, out_dir, json, solver;
  int target_elements = 0;
  int frame_interval = 5;
  double max_lesion_error_mm = 0.0;
  std::string error_curve;
  bool model_only = false, quiet = false, no_sliding = false, no_morphing = false;
  int coarse_elements = -1;  // -1: the case file's coarse_start.elements
};

/// The number after `option`: a whole number if `whole`, at least `min` (strictly above it if
/// `exclusive`). @throws std::invalid_argument naming the option and the value.
double number(const std::string& option, const std::string& v, bool whole, double min, bool exclusive) {
  double x = 0.0;
  size_t used = 0;
  try {
    x = whole ? static_cast<double>(std::stoi(v, &used)) : std::stod(v, &used);
  } catch (...) {
    used = 0;
  }
  if (used == 0 || used != v.size())
    throw std::invalid_argument(option + " '" + v + "' is not " + (whole ? "a whole number" : "a number"));
  if (exclusive ? !(x > min) : !(x >= min))
    throw std::invalid_argument(option + " must be " + (exclusive ? "positive" : "0 or positive") + ", got " + v);
  return x;
}

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
    else if (k == "--solver") a.solver = value();
    else if (k == "--model-only") a.model_only = true;
    else if (k == "--quiet") a.quiet = true;
    else if (k == "--no-sliding") a.no_sliding = true;
    else if (k == "--error-curve") a.error_curve = value();
    else if (k == "--max-lesion-error-mm") a.max_lesion_error_mm = number(k, value(), false, 0.0, true);
    else if (k == "--no-morphing") a.no_morphing = true;
    else if (k == "--coarse-elements") a.coarse_elements = static_cast<int>(number(k, value(), true, 0.0, false));
    else if (k == "--frames") a.frame_interval = static_cast<int>(number(k, value(), true, 0.0, false));
    else if (k == "--target-elements") a.target_elements = static_cast<int>(number(k, value(), true, 0.0, true)); else if (k == "-h" || k == "--help") {
      std::cout << kUsage;
      std::exit(0);
    } else throw std::invalid_argument("unknown option '" + k + "'\n" + kUsage);
  }
  if (a.max_lesion_error_mm > 0 && a.error_curve.empty())
    throw std::invalid_argument("--max-lesion-error-mm needs --error-curve FILE (bench_speed_accuracy --json output, e.g. "
                                "docs/speed_accuracy/sweep_supine.json)");
  if (a.case_file.empty() || a.out_dir.empty()) throw std::invalid_argument(std::string("--case and --out are required\n") + kUsage);
  return a;
}

void progressBar(const PipelineProgress& p) {
  // In a log (not a terminal) one line every 10 steps instead of a redrawn bar.
  static const bool tty = isatty(fileno(stderr));
  char detail[96];
  if (p.surface_mean_m >= 0)
    std::snprintf(detail, sizeof detail, "surface mean %.2f mm, p95 %.2f mm", p.surface_mean_m * 1e3, p.surface_p95_m * 1e3);
  else
    std::snprintf(detail, sizeof detail, "largest change %.4f mm", p.increment_m * 1e3);
  if (!tty) {
    if (p.step % 10 == 0 || p.step == 1)
      std::fprintf(stderr, "  %-9s step %d/%d, %s\n", stageName(p.stage), p.step, p.max_steps, detail);
    return;
  }
  const int width = 30, filled = static_cast<int>(p.fraction * width);
  std::fprintf(stderr, "\r  %-9s [%s%s] step %d/%d, %s   ", stageName(p.stage), std::string(filled, '#').c_str(),
               std::string(width - filled, ' ').c_str(), p.step, p.max_steps, detail);
  std::fflush(stderr);
}

/// The current deformed state as a .vtu: positions, displacement and sliding per node; von Mises
/// stress and modulus factor per element.
// A lesion's confidence region in millimetres, for lesions.json.
nlohmann::json regionJson(const LesionRegion& r, int samples) {
  nlohmann::json cov = nlohmann::json::array(), axes = nlohmann::json::array();
  for (int i = 0; i < 3; ++i) {
    cov.push_back({r.covariance_m2(i, 0) * 1e6, r.covariance_m2(i, 1) * 1e6, r.covariance_m2(i, 2) * 1e6});
    axes.push_back({r.axes(0, i), r.axes(1, i), r.axes(2, i)});  // row i: the unit vector of semi-axis i
  }
  return {{"confidence", r.confidence}, {"samples", samples}, {"covariance_mm2", cov},
          {"semi_axes_mm", {r.semi_axes_m.x() * 1e3, r.semi_axes_m.y() * 1e3, r.semi_axes_m.z() * 1e3}},
          {"axes", axes}, {"max_sample_distance_mm", r.max_sample_distance_m * 1e3}};
}

void writeDeformed(ProneToSupinePipeline& pipe, const SimulationModel& m, const std::string& path) {
  const Points u = pipe.displacement();
  const Points x = pipe.positions();
  MeshFields df;
  df.point_data.push_back({"displacement_mm", u * 1e3});
  if (pipe.sliding()) df.point_data.push_back({"sliding_mm", pipe.slidingVectors() * 1e3});
  df.cell_data.push_back({"von_mises_pa", pipe.vonMisesStress()});
  df.cell_data.push_back({"modulus_factor", pipe.modulusFactors()});
  MeshWriteOptions wo;
  wo.vtk.positions_m = &x;
  writeTetMesh(path, m.mesh, df, 1.0, wo);
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const Args args = parse(argc, argv);
    const auto t0 = std::chrono::steady_clock::now();
    ModelCase c = loadModelCaseWithMri(args.case_file);
    if (c.mesh && (args.target_elements > 0 || args.max_lesion_error_mm > 0))
      throw std::invalid_argument(std::string(args.target_elements > 0 ? "--target-elements" : "--max-lesion-error-mm") +
                                  " chooses how an image is meshed, but case '" + c.name +
                                  "' brings its own mesh (mesh:): leave the option out");
    if (args.target_elements > 0) c.meshing.target_elements = args.target_elements;
    PipelineSettings settings = loadPipelineSettings(args.case_file);
    if (!args.solver.empty()) settings.simulation.solver.kind = SolverSettings::kindFromName(args.solver);
    if (args.no_sliding) settings.simulation.sliding = false;
    if (args.coarse_elements >= 0) settings.coarse_start.elements = args.coarse_elements;
    if (args.no_morphing) settings.morphing.enabled = false;  // (also no coarse start: the model settles in that stage)
    // Model no more than the scene needs: the coarsest mesh whose measured lesion error meets the request.
    ModelChoice choice;
    if (args.max_lesion_error_mm > 0) {
      const std::string method = std::string(settings.simulation.stiffening ? "corotated+stiffening/" : "corotated/") +
                                 SolverSettings::kindName(settings.simulation.solver.kind);
      choice = chooseCoarsestModel(loadErrorCurve(args.error_curve, method, ErrorMeasure::kLesionMax), args.max_lesion_error_mm);
      c.meshing.target_elements = choice.target_elements;
      std::fprintf(stderr, "  model choice: %s\n", choice.explanation.c_str());
    }
    const double t_case = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const SimulationModel m = buildSimulationModel(c);
    const double t_model = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

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

    const double mesh_volume = m.mesh.volume();
    nlohmann::json metrics;  // of the simulation, when it runs
    nlohmann::json s;
    if (c.mri) {
      // The segmentation the model is built from: labels, cross-sections and summary.
      const MriCase& mri = *c.mri;
      writeLabelImage((out / "prone_labels.nrrd").string(), c.image);
      MriSectionRow row;
      row.title = "prone T1 " + fs::path(mri.source.path).filename().string() + " with its segmentation";
      row.image = &mri.volume.image;
      row.labels = &c.image;
      writeMriCrossSections((out / "segmentation.png").string(), {row});
      nlohmann::json seg = breast_sim::tools::segmentationJson(mri.volume, mri.segmentation, mri.read_seconds,
                                                               mri.scores ? &*mri.scores : nullptr, mri.source.truth);
      seg["breasts"] = breastsName(mri.source.breasts);
      if (!std::isnan(mri.midline_x_m)) seg["midline_x_mm"] = mri.midline_x_m * 1e3;
      nlohmann::json simulated = nlohmann::json::array();
      for (const Eigen::Vector3d& n : mri.nipples_m) simulated.push_back({1e3 * n.x(), 1e3 * n.y(), 1e3 * n.z()});
      seg["simulated_nipples_mm"] = simulated;
      std::ofstream(out / "segmentation.json") << seg.dump(2) << '\n';
      s["segmentation"] = seg;
    }
    s["case"] = c.name;
    s["elements"] = m.mesh.numTets();
    s["nodes"] = m.mesh.numNodes();
    s["node_sets"] = nlohmann::json::object();
    for (const auto& kv : m.mesh.nodeSets()) s["node_sets"][kv.first] = kv.second.size();
    s["boundary_faces"] = m.mesh.boundary().triangles.rows();
    if (args.max_lesion_error_mm > 0)
      s["model_choice"] = {{"max_lesion_error_mm", args.max_lesion_error_mm}, {"met", choice.met},
                           {"target_elements", choice.target_elements}, {"expected_lesion_error_mm", choice.expected_error_mm},
                           {"expected_seconds", choice.expected_seconds}, {"explanation", choice.explanation},
                           {"error_curve", args.error_curve}};
    s["prone_gravity_direction"] = {c.prone_gravity_direction.x(), c.prone_gravity_direction.y(), c.prone_gravity_direction.z()};
    s["boundary_closed"] = isClosedManifold(m.mesh.boundary().triangles);
    s["seconds"] = {{"case_and_image", t_case}, {"meshing", m.meshing.seconds}, {"model_total", t_model}};
    if (c.mesh)
      s["mesh_file"] = {{"path", c.mesh_source.path},
                        {"file_nodes", c.mesh_report.file_nodes},
                        {"unused_nodes_dropped", c.mesh_report.unused_nodes},
                        {"label_image_voxel_mm", c.mesh_source.voxel_size_m * 1e3},
                        {"label_image_seconds", c.mesh_report.voxelize_seconds}};
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

    // The prone-to-supine pipeline: gravity with stiffening (and sliding), then morphing.
    std::vector<Points> lesion_rows;  // after gravity, final
    std::optional<LesionUncertainty> uncertainty;  // with `uncertainty:` enabled
    std::unique_ptr<ProneToSupinePipeline> pipe;
    nlohmann::json supine_mri;  // an MRI case's simulated supine MRI
    bool ok = true;
    if (!args.model_only) {
      const auto ts = std::chrono::steady_clock::now();
      pipe = std::make_unique<ProneToSupinePipeline>(c, m, settings);
      const double t_setup = std::chrono::duration<double>(std::chrono::steady_clock::now() - ts).count();
      // ParaView series: a frame every `frame_interval` accepted steps of each stage, and each stage's end.
      const fs::path series_dir = out / "series";
      fs::remove_all(series_dir);
      fs::create_directories(series_dir);
      std::vector<std::pair<double, std::string>> frames;
      double sim_time = 0.0;
      auto writeFrame = [&](const std::string& tag) {
        // With coarse_start the first frames are of the coarse model (the one that is stepping).
        const ProneToSupinePipeline& running = pipe->running();
        const Points u = running.displacement();
        const Points x = running.positions();
        MeshFields ff;
        ff.point_data.push_back({"displacement_mm", u * 1e3});
        MeshWriteOptions wo;
        wo.vtk.positions_m = &x;
        char name[64];
        std::snprintf(name, sizeof name, "frame_%04zu.vtu", frames.size());
        writeTetMesh((series_dir / name).string(), running.model().mesh, ff, 1.0, wo);
        frames.push_back({sim_time, std::string("series/") + name});
        (void)tag;
      };
      if (args.frame_interval > 0) writeFrame("prone");
      PipelineStage last_stage = PipelineStage::kIdle;
      int last_step = -1;
      auto progress = [&](const PipelineProgress& p) {
        if (p.stage != last_stage) {
          if (!args.quiet && isatty(fileno(stderr)) && last_stage != PipelineStage::kIdle) std::fprintf(stderr, "\n");
          last_stage = p.stage;
          last_step = -1;
        }
        if (p.step != last_step) {
          sim_time += pipe->running().simulator().params().time_step_s;
          if (args.frame_interval > 0 && p.step % args.frame_interval == 0) writeFrame(stageName(p.stage));
          last_step = p.step;
        }
        if (!args.quiet) progressBar(p);
      };
      pipe->runGravity(progress);
      if (!args.quiet && isatty(fileno(stderr))) std::fprintf(stderr, "\n");
      writeDeformed(*pipe, m, (out / "supine_gravity.vtu").string());
      lesion_rows.push_back(pipe->lesionPositions());
      const PipelineMetrics gravity_metrics = pipe->metrics();
      const Points x_gravity = pipe->positions();
      const Points slide_gravity = pipe->slidingVectors();
      const bool morph = settings.morphing.enabled && pipe->hasTarget();
      if (morph) {
        last_stage = PipelineStage::kIdle;
        pipe->runMorphing(progress);
        if (!args.quiet && isatty(fileno(stderr))) std::fprintf(stderr, "\n");
        lesion_rows.push_back(pipe->lesionPositions());
      }
      if (args.frame_interval > 0) writeFrame("final");
      writeDeformed(*pipe, m, (out / "supine.vtu").string());
      if (pipe->sliding()) {
        // The chest-wall nodes' sliding vectors (seed Figure 4 b, c), for plots (scripts/plot_sliding.py).
        const Points slide_final = pipe->slidingVectors();
        std::ofstream sc(out / "sliding.csv");
        sc << "node,x_mm,y_mm,z_mm,gravity_dx_mm,gravity_dy_mm,gravity_dz_mm,final_dx_mm,final_dy_mm,final_dz_mm\n";
        for (int v : m.mesh.nodeSet(node_sets::kChestWall)) {
          const Eigen::RowVector3d r = 1e3 * m.mesh.nodes().row(v), a = 1e3 * slide_gravity.row(v), b = 1e3 * slide_final.row(v);
          sc << v << ',' << r.x() << ',' << r.y() << ',' << r.z() << ',' << a.x() << ',' << a.y() << ',' << a.z() << ','
             << b.x() << ',' << b.y() << ',' << b.z() << '\n';
        }
      }
      {
        std::ofstream pvd(out / "series.pvd");
        pvd << "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\">\n  <Collection>\n";
        for (const auto& f : frames)
          pvd << "    <DataSet timestep=\"" << f.first << "\" part=\"0\" file=\"" << f.second << "\"/>\n";
        pvd << "  </Collection>\n</VTKFile>\n";
      }
      const PipelineMetrics fm = pipe->metrics();
      // Cross-sections: prone, after gravity, final (with the target's outline).
      {
        std::vector<CrossSectionConfiguration> rows(morph ? 3 : 2);
        const Points x_final = pipe->positions();
        rows[0].title = "prone (model of the MRI)";
        rows[0].lesions_m = m.lesion_embedding.positions(m.mesh.nodes());
        rows[1].title = "supine, gravity" + std::string(settings.simulation.sliding ? " + sliding" : "") +
                        (settings.simulation.stiffening ? " + stiffening" : "");
        rows[1].positions_m = &x_gravity;
        rows[1].lesions_m = lesion_rows[0];
        if (pipe->hasTarget()) {
          rows[1].outline_vertices_m = pipe->target().vertices_m;
          rows[1].outline_triangles = pipe->target().triangles;
        }
        if (morph) {
          rows[2] = rows[1];
          rows[2].title = "supine, after morphing to the target (red)";
          rows[2].positions_m = &x_final;
          rows[2].lesions_m = lesion_rows.back();
        }
        CrossSectionOptions co;
        co.centre_m = m.lesion_embedding.positions(m.mesh.nodes()).colwise().mean().transpose();
        if (m.lesions.empty()) co.centre_m.setConstant(std::numeric_limits<double>::quiet_NaN());
        writeCrossSections((out / "cross_sections.png").string(), m.mesh, rows, co);
      }
      if (c.mri) {
        // The simulated supine MRI of the final state (seed Figure 4e).
        const Points u = pipe->positions() - m.mesh.nodes();
        const SupineImages supine = simulatedSupineMri(*c.mri, m.mesh, u);
        writeMriVolume((out / "supine_mri.nii.gz").string(), supine.image);
        writeMriVolume((out / "supine_mri.nrrd").string(), supine.image);
        writeLabelImage((out / "supine_labels.nrrd").string(), supine.labels);
        MriSectionRow prone_row, supine_row;
        prone_row.title = "prone MRI with its segmentation";
        prone_row.image = &c.mri->volume.image;
        prone_row.labels = &c.image;
        supine_row.title = "simulated supine MRI, labels carried along";
        supine_row.image = &supine.image;
        supine_row.labels = &supine.labels;
        MriSectionOptions so;
        if (!m.lesions.empty()) so.centre_m = m.lesions.front().position_m;
        writeMriCrossSections((out / "supine_mri.png").string(), {prone_row, supine_row}, so);
        const ImageGeometry& sg = supine.image.geometry;
        supine_mri = {{"size", {sg.size.x(), sg.size.y(), sg.size.z()}},
                      {"spacing_mm", {1e3 * sg.spacing_m.x(), 1e3 * sg.spacing_m.y(), 1e3 * sg.spacing_m.z()}},
                      {"body_voxels", supine.body_voxels},
                      {"seconds", supine.seconds},
                      {"files", {"supine_mri.nii.gz", "supine_mri.nrrd", "supine_labels.nrrd", "supine_mri.png"}}};
      }
      const StageReport& g = pipe->gravityReport();
      const StageReport& sl = pipe->slidingReport();
      const StageReport& mo = pipe->morphingReport();
      auto stage = [](const StageReport& r) {
        nlohmann::json j = {{"ran", r.ran}, {"converged", r.converged}, {"steps", r.steps}, {"reversed_steps", r.reversed_steps},
                            {"reversal_limit_hits", r.reversal_limit_hits}, {"stuck", r.stuck}, {"seconds", r.seconds},
                            {"last_increment_mm", r.last_increment_m * 1e3}, {"final_alpha_per_pa", r.final_alpha_per_pa},
                            {"modulus_excess", r.modulus_excess}, {"locally_stiffened_elements", r.locally_stiffened_elements},
                            {"locally_stiffened_volume_percent", r.locally_stiffened_volume_percent},
                            {"elements", r.elements}};
        if (r.coarse_elements > 0)
          j["coarse_start"] = {{"elements", r.coarse_elements}, {"steps", r.coarse_steps}, {"reversed_steps", r.coarse_reversed_steps}};
        if (r.surface_mean_m >= 0) j["pulled_vertices_to_target_mm"] = {{"mean", r.surface_mean_m * 1e3}, {"p95", r.surface_p95_m * 1e3}};
        if (r.max_slide_m > 0) j["max_slide_mm"] = r.max_slide_m * 1e3;
        return j;
      };
      auto deformation = [](const PipelineMetrics& pm) {
        nlohmann::json j = {{"inverted_elements", pm.inverted_elements}, {"volume_change_percent", pm.volume_change_percent},
                            {"max_displacement_mm", pm.max_displacement_m * 1e3}, {"max_modulus_factor", pm.max_modulus_factor},
                            {"alpha_per_pa", pm.final_alpha_per_pa}};
        if (pm.has_target) {
          auto d = [](const DistanceStats& st) { return nlohmann::json{{"mean", st.mean_m * 1e3}, {"p95", st.p95_m * 1e3}, {"max", st.max_m * 1e3}}; };
          // Target → skin over the target's skin only: its samples on the model's chest wall are left out.
          j["surface_distance_mm"] = {{"skin_to_target", d(pm.surface.model_to_target)},
                                      {"target_skin_to_skin", d(pm.surface.target_to_model)}};
          j["surface_samples"] = {{"skin", pm.surface.model_to_target.count},
                                  {"target", pm.surface.target_samples},
                                  {"target_on_chest_wall_left_out", pm.surface.target_on_chest_wall}};
        }
        return j;
      };
      const Eigen::Vector3d g_load = pipe->supineGravityLoad();
      // The rest shape: the unloaded one's recovery (residual of X0 re-loaded prone, its distance to prone).
      const UnloadedStateResult& un = pipe->unloadedState();
      const bool unloaded =
          pipe->settings().simulation.reference_state == SimulationSettings::ReferenceState::kUnloaded;
      nlohmann::json reference = {{"shape", unloaded ? "unloaded" : "prone"}};
      if (unloaded) {
        const Eigen::VectorXd gap = (pipe->model().mesh.nodes() - m.mesh.nodes()).rowwise().norm();
        reference["iterations"] = un.iterations;
        reference["max_residual_mm"] = un.max_residual_m * 1e3;
        reference["mean_residual_mm"] = un.mean_residual_m * 1e3;
        reference["unloaded_to_prone_mm"] = {{"mean", gap.mean() * 1e3}, {"max", gap.maxCoeff() * 1e3}};
        reference["seconds"] = un.seconds;
      }
      const double t_sim = std::chrono::duration<double>(std::chrono::steady_clock::now() - ts).count();
      metrics = {{"case", c.name},
                 {"elements", m.mesh.numTets()},
                 {"nodes", m.mesh.numNodes()},
                 {"gravity_load_mps2", {g_load.x(), g_load.y(), g_load.z()}},
                 {"solver", SolverSettings::kindName(settings.simulation.solver.kind)},
                 {"multigrid_levels", pipe->build().multigrid_levels},
                 {"youngs_modulus_pa", settings.simulation.material.youngs_modulus_pa},
                 {"poisson_ratio", settings.simulation.material.poisson_ratio},
                 {"stiffening", settings.simulation.stiffening},
                 {"sliding", settings.simulation.sliding},
                 {"reference_state", reference},
                 {"morphing", morph},
                 {"stages", {{"gravity", stage(g)}, {"sliding", stage(sl)}, {"morphing", stage(mo)}}},
                 {"after_gravity", deformation(gravity_metrics)},
                 {"final", deformation(fm)},
                 {"steps", g.steps + sl.steps + mo.coarse_steps + mo.steps},
                 {"reversed_steps", g.reversed_steps + sl.reversed_steps + mo.coarse_reversed_steps + mo.reversed_steps},
                 {"seconds", {{"setup", t_setup - un.seconds}, {"unloaded_shape", un.seconds}, {"gravity", g.seconds}, {"sliding", sl.seconds},
                              {"morphing", mo.seconds}, {"compute", un.seconds + g.seconds + sl.seconds + mo.seconds},
                              {"total_with_output", t_sim}}},
                 {"vtu_frames", frames.size()}};
      // Where the morphing did not reach: the pulled skin vertices farther from the target than the
      // stage's mean tolerance at the end, and how many of them lie in the wall band (sliding nodes
      // and their elements), where the wall's hold and the pull meet.
      if (morph && pipe->morphing()) {
        const SurfaceMorphing& sm = *pipe->morphing();
        std::vector<char> band(static_cast<size_t>(pipe->model().mesh.numNodes()), 0);
        for (int n : pipe->wallBandNodes()) band[static_cast<size_t>(n)] = 1;
        int off = 0, off_band = 0;
        for (size_t k = 0; k < sm.vertices().size(); ++k) {
          if (!(std::abs(sm.lastDistances()[static_cast<Eigen::Index>(k)]) > settings.morphing.tolerance_mean_m)) continue;
          ++off;
          off_band += band[static_cast<size_t>(sm.vertices()[k])];
        }
        metrics["stages"]["morphing"]["pulled_vertices_off_target"] = {
            {"beyond_mm", settings.morphing.tolerance_mean_m * 1e3}, {"pulled", sm.vertices().size()},
            {"count", off}, {"in_wall_band", off_band}};
      }
      if (!supine_mri.is_null()) metrics["supine_mri"] = supine_mri;
      ok = g.converged && (!sl.ran || sl.converged) && (!morph || mo.converged) && fm.inverted_elements == 0;
      metrics["completed"] = ok;
      // The lesions' confidence regions: the ensemble over stiffness, Poisson ratio and path.
      if (ok && settings.uncertainty.enabled && !m.lesions.empty()) {
        const int count = settings.uncertainty.samples;
        int shown = -1;
        uncertainty = estimateLesionUncertainty(c, m, settings, lesion_rows.back(), [&](int i, int n, const PipelineProgress&) {
          if (args.quiet || i == shown) return;
          shown = i;
          std::fprintf(stderr, "  uncertainty: sample %d of %d\n", i + 1, n);
        }, nullptr, 1, pipe.get());
        nlohmann::json js = nlohmann::json::array();
        for (const UncertaintySample& u : uncertainty->samples)
          js.push_back({{"youngs_modulus_factor", u.params.youngs_modulus_factor}, {"poisson_ratio", u.params.poisson_ratio},
                        {"time_step_factor", u.params.time_step_factor}, {"completed", u.completed},
                        {"failure", u.failure}, {"note", u.note}, {"unloaded_loadings", u.unloaded_loadings},
                        {"unloaded_residual_mm", u.unloaded_residual_m * 1e3},
                        {"seconds", u.seconds}});
        const double single = metrics["seconds"]["compute"].get<double>();
        metrics["uncertainty"] = {{"valid", uncertainty->valid}, {"failure", uncertainty->failure},
                                  {"samples_requested", count}, {"samples", js}, {"seconds", uncertainty->seconds},
                                  {"cost_vs_run", single > 0 ? uncertainty->seconds / single : 0.0}};
        ok = uncertainty->valid;
        metrics["completed"] = ok;
      }
    }

    nlohmann::json lesions = nlohmann::json::array();
    std::ofstream csv(out / "lesions.csv");
    const char* stage_names[2] = {"gravity", "supine"};
    csv << "name,prone_x_mm,prone_y_mm,prone_z_mm,radius_mm,tet,outside_mm";
    for (size_t k = 0; k < lesion_rows.size(); ++k)
      csv << ',' << stage_names[k] << "_x_mm," << stage_names[k] << "_y_mm," << stage_names[k] << "_z_mm," << stage_names[k] << "_moved_mm";
    if (uncertainty && uncertainty->valid)
      csv << ",region_confidence,region_semi_axis_1_mm,region_semi_axis_2_mm,region_semi_axis_3_mm,region_max_sample_distance_mm";
    csv << '\n';
    for (size_t i = 0; i < m.lesions.size(); ++i) {
      const auto& l = m.lesions[i];
      const auto& e = m.lesion_embedding.points()[i];
      const Eigen::Vector3d p = l.position_m * 1e3;
      csv << l.name << ',' << p.x() << ',' << p.y() << ',' << p.z() << ',' << l.radius_m * 1e3 << ',' << e.tet << ','
          << e.outside_distance_m * 1e3;
      nlohmann::json j = {{"name", l.name}, {"prone_mm", {p.x(), p.y(), p.z()}}, {"radius_mm", l.radius_m * 1e3}, {"tet", e.tet}};
      for (size_t k = 0; k < lesion_rows.size(); ++k) {
        const Eigen::Vector3d q = lesion_rows[k].row(static_cast<Eigen::Index>(i)).transpose() * 1e3;
        csv << ',' << q.x() << ',' << q.y() << ',' << q.z() << ',' << (q - p).norm();
        j[std::string(stage_names[k]) + "_mm"] = {q.x(), q.y(), q.z()};
        j[std::string(stage_names[k]) + "_moved_mm"] = (q - p).norm();
      }
      if (uncertainty && uncertainty->valid) {
        const LesionRegion& r = uncertainty->lesions[i];
        csv << ',' << r.confidence << ',' << r.semi_axes_m.x() * 1e3 << ',' << r.semi_axes_m.y() * 1e3 << ','
            << r.semi_axes_m.z() * 1e3 << ',' << r.max_sample_distance_m * 1e3;
        j["supine_region"] = regionJson(r, static_cast<int>(uncertainty->samples.size()));
      }
      csv << '\n';
      lesions.push_back(j);
    }
    std::ofstream(out / "lesions.json") << lesions.dump(2) << '\n';
    std::ofstream(out / "case_effective.yaml")
        << "# The case as this run used it: every key with its value (docs/case_files.md).\n"
        << effectiveCaseYaml(args.case_file, c.meshing, c.lesion_snap_tolerance_m, settings);
    s["lesions"] = lesions;
    s["seconds"]["total"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::ofstream(out / "model_summary.json") << s.dump(2) << '\n';
    if (!metrics.is_null()) {
      metrics["lesions"] = lesions;
      std::ofstream(out / "metrics.json") << metrics.dump(2) << '\n';
    }
    if (!args.json.empty()) std::ofstream(args.json) << (metrics.is_null() ? s : metrics).dump(2) << '\n';

    std::printf("breast_sim run of case '%s'\n", c.name.c_str());
    std::printf("  %-26s %d tetrahedra, %d nodes (%s boundary), %.2f s (%s %.2f s)\n", "model", m.mesh.numTets(),
                m.mesh.numNodes(), s["boundary_closed"].get<bool>() ? "closed" : "OPEN", t_model,
                c.mesh ? "read from the file; its label image" : "meshing", m.meshing.seconds);
    std::printf("  %-26s %.1f cm3", "volume", mesh_volume * 1e6);
    if (c.phantom) std::printf(" (analytic %.1f, error %+.2f%%)", c.phantom->prone_volume_m3 * 1e6,
                               100.0 * (mesh_volume / c.phantom->prone_volume_m3 - 1.0));
    std::printf(", quality: %d inverted, min dihedral %.1f deg\n", m.quality.num_inverted, m.quality.min_dihedral_deg);
    if (c.mri) {
      const MriCase& mri = *c.mri;
      const SegmentationReport& r = mri.segmentation.report;
      const ImageGeometry& g = mri.volume.image.geometry;
      std::printf("  %-26s %s (%s, %d x %d x %d voxels of %.2f mm), read in %.2f s\n", "prone MRI", mri.source.path.c_str(),
                  mri.volume.info.format.c_str(), g.size.x(), g.size.y(), g.size.z(), 1e3 * g.spacing_m.minCoeff(), mri.read_seconds);
      std::printf("  %-26s %.2f s: fat %.1f ml, fibroglandular %.1f ml, lesion %.1f ml; chest wall measured in %.0f %% of "
                  "the breast's columns; %zu nipple(s), breasts: %s\n",
                  "segmentation", r.seconds_total, r.volume_ml[1], r.volume_ml[2], r.volume_ml[4], 100.0 * r.boundary_coverage,
                  mri.nipples_m.size(), breastsName(mri.source.breasts));
      if (mri.scores)
        std::printf("  %-26s %s\n", "segmentation vs truth", breast_sim::tools::scoresLine(*mri.scores).c_str());
    }
    if (!metrics.is_null()) {
      const auto& st = metrics["stages"];
      auto line = [&](const char* name, const nlohmann::json& r, const char* extra) {
        if (!r["ran"].get<bool>()) return;
        if (!settings.simulation.stiffening) {
          std::printf("  %-26s %s in %d steps, %.2f s (no stiffening)%s\n", name,
                      r["converged"].get<bool>() ? "converged" : "NOT converged", r["steps"].get<int>(),
                      r["seconds"].get<double>(), extra);
          return;
        }
        std::printf("  %-26s %s in %d steps, %.2f s, %ld reversed, alpha %.3g 1/Pa%s\n", name,
                    r["converged"].get<bool>() ? "converged"
                    : r["stuck"].get<bool>()   ? "STUCK (no step without inverting)"
                                               : "NOT converged", r["steps"].get<int>(),
                    r["seconds"].get<double>(), r["reversed_steps"].get<long>(), r["final_alpha_per_pa"].get<double>(), extra);
      };
      auto on = [&](const nlohmann::json& r) {  // the stage ran on the coarse model (coarse_start)
        static char b[96];
        b[0] = 0;
        if (r.contains("elements") && r["elements"].get<int>() != m.mesh.numTets())
          std::snprintf(b, sizeof b, " (on the %d-element coarse model)", r["elements"].get<int>());
        if (r.contains("coarse_start"))
          std::snprintf(b, sizeof b, " (after %d steps, %ld reversed, on the %d-element coarse model)",
                        r["coarse_start"]["steps"].get<int>(), r["coarse_start"]["reversed_steps"].get<long>(),
                        r["coarse_start"]["elements"].get<int>());
        return std::string(b);
      };
      char slide[64] = "";
      if (st["sliding"].contains("max_slide_mm")) std::snprintf(slide, sizeof slide, ", largest slide %.1f mm", st["sliding"]["max_slide_mm"].get<double>());
      const auto& ref = metrics["reference_state"];
      if (ref["shape"] == "unloaded")
        std::printf("  %-26s %d loadings, %.2f s, re-loaded within %.4f mm of prone; %.2f mm mean / %.2f mm max from it\n",
                    "unloaded shape", ref["iterations"].get<int>(), ref["seconds"].get<double>(),
                    ref["max_residual_mm"].get<double>(), ref["unloaded_to_prone_mm"]["mean"].get<double>(),
                    ref["unloaded_to_prone_mm"]["max"].get<double>());
      line("gravity (wall fixed)", st["gravity"], on(st["gravity"]).c_str());
      line("gravity with sliding", st["sliding"], (slide + on(st["sliding"])).c_str());
      line("surface morphing", st["morphing"], on(st["morphing"]).c_str());
      auto deformed = [&](const char* name, const nlohmann::json& d) {
        std::printf("  %-26s %d inverted, volume %+.2f%%, max displacement %.1f mm", name, d["inverted_elements"].get<int>(),
                    d["volume_change_percent"].get<double>(), d["max_displacement_mm"].get<double>());
        if (d.contains("surface_distance_mm"))
          std::printf(", surface distance mean/p95 %.2f/%.2f mm (skin->target), %.2f/%.2f mm (target skin->skin; "
                      "%d of %d target samples on the chest wall left out)",
                      d["surface_distance_mm"]["skin_to_target"]["mean"].get<double>(), d["surface_distance_mm"]["skin_to_target"]["p95"].get<double>(),
                      d["surface_distance_mm"]["target_skin_to_skin"]["mean"].get<double>(),
                      d["surface_distance_mm"]["target_skin_to_skin"]["p95"].get<double>(),
                      d["surface_samples"]["target_on_chest_wall_left_out"].get<int>(), d["surface_samples"]["target"].get<int>());
        std::printf("\n");
      };
      deformed("after gravity", metrics["after_gravity"]);
      if (metrics["morphing"].get<bool>()) deformed("after morphing", metrics["final"]);
      std::printf("  %-26s %.2f s (setup %.2f s)\n", "compute", metrics["seconds"]["compute"].get<double>(),
                  metrics["seconds"]["setup"].get<double>());
      if (metrics.contains("uncertainty")) {
        const auto& u = metrics["uncertainty"];
        if (u["valid"].get<bool>())
          std::printf("  %-26s %zu samples, %.2f s (%.1fx the run)\n", "lesion regions", u["samples"].size(),
                      u["seconds"].get<double>(), u["cost_vs_run"].get<double>());
        else
          std::printf("  %-26s NONE: %s\n", "lesion regions", u["failure"].get<std::string>().c_str());
      }
    }
    for (const auto& l : lesions) {
      std::printf("  lesion %-19s prone (%.1f, %.1f, %.1f) mm", l["name"].get<std::string>().c_str(),
                  l["prone_mm"][0].get<double>(), l["prone_mm"][1].get<double>(), l["prone_mm"][2].get<double>());
      if (l.contains("supine_mm"))
        std::printf(" -> supine (%.1f, %.1f, %.1f) mm, moved %.1f mm", l["supine_mm"][0].get<double>(),
                    l["supine_mm"][1].get<double>(), l["supine_mm"][2].get<double>(), l["supine_moved_mm"].get<double>());
      else if (l.contains("gravity_mm"))
        std::printf(" -> (%.1f, %.1f, %.1f) mm after gravity, moved %.1f mm", l["gravity_mm"][0].get<double>(),
                    l["gravity_mm"][1].get<double>(), l["gravity_mm"][2].get<double>(), l["gravity_moved_mm"].get<double>());
      if (l.contains("supine_region")) {
        const auto& r = l["supine_region"];
        std::printf(", %.0f%% region: semi-axes %.1f x %.1f x %.1f mm", 100.0 * r["confidence"].get<double>(),
                    r["semi_axes_mm"][0].get<double>(), r["semi_axes_mm"][1].get<double>(), r["semi_axes_mm"][2].get<double>());
      }
      std::printf("\n");
    }
    if (!supine_mri.is_null())
      std::printf("  %-26s %d x %d x %d voxels, %ld in the body, %.2f s: supine_mri.nii.gz, supine_mri.nrrd\n", "simulated supine MRI",
                  supine_mri["size"][0].get<int>(), supine_mri["size"][1].get<int>(), supine_mri["size"][2].get<int>(),
                  supine_mri["body_voxels"].get<long>(), supine_mri["seconds"].get<double>());
    std::printf("  %-26s %s\n", "written to", fs::absolute(out).string().c_str());
    return ok || args.model_only ? 0 : 3;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "breast_sim_run: error: %s\n", e.what());
    return 2;
  }
}
