#pragma once
/// @file gmsh_element_types.h
/// Gmsh element types as the MSH reader (gmsh_read.cpp) and writer (gmsh_write.cpp) need them;
/// private to src/core/mesh. Reference: Gmsh reference manual, section "MSH file format".

namespace breast_sim::core::gmsh_detail {

/// Element type number of the 4-node tetrahedron.
constexpr int kTet4 = 4;

// Nodes per element of Gmsh's element types up to 4th order; -1 for types we do not know, which a
// text file can still skip line by line but a binary file cannot.
inline int gmshNodesPerElement(long long type) {
  switch (type) {
    case 1: return 2;    case 2: return 3;    case 3: return 4;    case 4: return 4;
    case 5: return 8;    case 6: return 6;    case 7: return 5;    case 8: return 3;
    case 9: return 6;    case 10: return 9;   case 11: return 10;  case 12: return 27;
    case 13: return 18;  case 14: return 14;  case 15: return 1;   case 16: return 8;
    case 17: return 20;  case 18: return 15;  case 19: return 13;  case 20: return 9;
    case 21: return 10;  case 22: return 12;  case 23: return 15;  case 24: return 15;
    case 25: return 21;  case 26: return 4;   case 27: return 5;   case 28: return 6;
    case 29: return 20;  case 30: return 35;  case 31: return 56;  case 92: return 64;
    case 93: return 125;
    default: return -1;
  }
}

/// Dimension of an element type: 0 point, 1 line, 2 surface, 3 volume (and types not listed).
inline int gmshElementDimension(long long type) {
  switch (type) {
    case 15: return 0;
    case 1: case 8: case 26: case 27: case 28: return 1;
    case 2: case 3: case 9: case 10: case 16: case 20: case 21: case 22: case 23: case 24: case 25:
      return 2;
    default: return 3;
  }
}

}  // namespace breast_sim::core::gmsh_detail
