#pragma once
/// @file tissue_labels.h
/// Which label values of a segmentation mean which tissue. Defaults follow the FDA VICTRE breast
/// phantom's labels (shared/data/victre-phantom/README.md), which our own phantom uses too.

#include <cstdint>
#include <set>
#include <string>

namespace breast_sim::core {

/// Tissue classes of the simulation model. The region label of an element is its class value.
enum class TissueClass : int {
  kAir = 0,
  kFat = 1,
  kFibroglandular = 2,
  kSkin = 3,
  kLesion = 4,
  kChestWall = 5,  ///< muscle / rib cage: not simulated, the breast rests on it
};

/// Human-readable name of a tissue class ("fat", "fibroglandular", …).
std::string tissueClassName(TissueClass c);

/// Label values of each tissue in an input label image. Labels in none of the sets are air.
struct TissueLabels {
  std::set<std::uint16_t> fat{1};
  std::set<std::uint16_t> fibroglandular{29, 88, 95, 125, 150, 225};
  std::set<std::uint16_t> skin{2, 33};
  std::set<std::uint16_t> lesion{200, 250};
  std::set<std::uint16_t> chest_wall{40};

  /// Class of a label value (air if it is in no set).
  TissueClass classify(std::uint16_t label) const;
  /// Whether the label is breast tissue (fat, fibroglandular, skin or lesion): the simulated body.
  bool isTissue(std::uint16_t label) const;
  /// @throws std::invalid_argument naming the label value when a label is in two sets.
  void validate() const;
};

/// Label values the built-in phantom writes (a subset of the VICTRE values).
namespace phantom_labels {
inline constexpr std::uint16_t kAir = 0;
inline constexpr std::uint16_t kFat = 1;
inline constexpr std::uint16_t kSkin = 2;
inline constexpr std::uint16_t kGland = 29;
inline constexpr std::uint16_t kNipple = 33;
inline constexpr std::uint16_t kChestWall = 40;
inline constexpr std::uint16_t kLesion = 200;
}  // namespace phantom_labels

}  // namespace breast_sim::core
