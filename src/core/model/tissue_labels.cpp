#include "breast_sim/core/model/tissue_labels.h"

#include <stdexcept>

namespace breast_sim::core {

std::string tissueClassName(TissueClass c) {
  switch (c) {
    case TissueClass::kAir: return "air";
    case TissueClass::kFat: return "fat";
    case TissueClass::kFibroglandular: return "fibroglandular";
    case TissueClass::kSkin: return "skin";
    case TissueClass::kLesion: return "lesion";
    case TissueClass::kChestWall: return "chest_wall";
  }
  return "unknown";
}

TissueClass TissueLabels::classify(std::uint16_t label) const {
  if (fat.count(label)) return TissueClass::kFat;
  if (fibroglandular.count(label)) return TissueClass::kFibroglandular;
  if (skin.count(label)) return TissueClass::kSkin;
  if (lesion.count(label)) return TissueClass::kLesion;
  if (chest_wall.count(label)) return TissueClass::kChestWall;
  return TissueClass::kAir;
}

bool TissueLabels::isTissue(std::uint16_t label) const {
  const TissueClass c = classify(label);
  return c != TissueClass::kAir && c != TissueClass::kChestWall;
}

void TissueLabels::validate() const {
  const std::set<std::uint16_t>* sets[] = {&fat, &fibroglandular, &skin, &lesion, &chest_wall};
  const char* names[] = {"fat", "fibroglandular", "skin", "lesion", "chest_wall"};
  for (int a = 0; a < 5; ++a)
    for (int b = a + 1; b < 5; ++b)
      for (auto v : *sets[a])
        if (sets[b]->count(v))
          throw std::invalid_argument("tissue labels: label " + std::to_string(v) + " is listed as both " +
                                      names[a] + " and " + names[b] + "; give each label one tissue");
  if (fat.empty() && fibroglandular.empty() && skin.empty() && lesion.empty())
    throw std::invalid_argument("tissue labels: no tissue label given; list at least one (e.g. fat: [1])");
}

}  // namespace breast_sim::core
