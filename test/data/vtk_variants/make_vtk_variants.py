#!/usr/bin/env python3
"""Writes the VTK files of test_mesh_io's VtkFilesOfEveryWriterVariantReadTheSame: one small grid
(a triangle and three tetrahedra on five points; cell arrays region and a 2-component field with
component names and an information key; point arrays of several types: short scalars, float vectors, vtkIdType, bits,
strings, int64, a node set) written by VTK's own writers in every variant a reader meets: legacy
file versions 4.2 and 5.1, ASCII and binary; XML ascii, inline base64 and appended raw or base64
data, uncompressed or zlib, LZ4 and LZMA blocks (64-byte blocks, so arrays span several), UInt32
and UInt64 headers. Run with Debian's python3-vtk9: /usr/bin/python3 make_vtk_variants.py"""
import os

import vtk

HERE = os.path.dirname(os.path.abspath(__file__))


def grid():
    points = vtk.vtkPoints()
    points.SetDataTypeToDouble()
    for p in [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, -0.5)]:
        points.InsertNextPoint(*p)
    g = vtk.vtkUnstructuredGrid()
    g.SetPoints(points)
    for cell_type, ids in [(vtk.VTK_TRIANGLE, (1, 2, 3)), (vtk.VTK_TETRA, (0, 1, 2, 3)),
                           (vtk.VTK_TETRA, (0, 1, 2, 4)), (vtk.VTK_TETRA, (1, 2, 4, 3))]:
        id_list = vtk.vtkIdList()
        for i in ids:
            id_list.InsertNextId(i)
        g.InsertNextCell(cell_type, id_list)

    def array(cls, name, values, components=1):
        a = cls()
        a.SetName(name)
        a.SetNumberOfComponents(components)
        for v in values:
            a.InsertNextValue(v)
        return a

    g.GetCellData().AddArray(array(vtk.vtkIntArray, "region", [5, 29, 29, 2]))
    stress = array(vtk.vtkDoubleArray, "von_mises_pa", [0, 0, 1, 10, 2, 20, 3, 30], 2)
    stress.SetComponentName(0, "a")
    stress.SetComponentName(1, "b")
    stress.GetInformation().Set(vtk.vtkAbstractArray.GUI_HIDE(), 1)  # written as METADATA / InformationKey
    g.GetCellData().AddArray(stress)
    g.GetPointData().AddArray(array(vtk.vtkUnsignedCharArray, "nodeset_skin", [0, 1, 1, 1, 0]))
    g.GetPointData().SetVectors(array(vtk.vtkFloatArray, "displacement_mm",
                                      [v for i in range(5) for v in (i, -i, 0.5 * i)], 3))
    g.GetPointData().SetScalars(array(vtk.vtkShortArray, "temperature", [1, -2, 3, -4, 5]))
    g.GetPointData().AddArray(array(vtk.vtkIdTypeArray, "ids", [10, 11, 12, 13, 14]))
    g.GetPointData().AddArray(array(vtk.vtkBitArray, "flags", [1, 0, 1, 1, 0]))
    g.GetPointData().AddArray(array(vtk.vtkStringArray, "names", ["a", "bb", "", "with spaces", "e"]))
    g.GetPointData().AddArray(array(vtk.vtkLongLongArray, "big", [1, 2, 3, 4, 2 ** 40]))
    g.GetFieldData().AddArray(array(vtk.vtkDoubleArray, "TIME", [1.5]))
    return g


def main():
    g = grid()
    for version in (42, 51):
        for binary in (False, True):
            w = vtk.vtkUnstructuredGridWriter()
            w.SetInputData(g)
            w.SetFileName(os.path.join(HERE, "legacy%d_%s.vtk" % (version, "binary" if binary else "ascii")))
            if version == 42:
                w.SetFileVersion(42)
            w.SetFileType(vtk.VTK_BINARY if binary else vtk.VTK_ASCII)
            w.Write()
    compressors = {"none": None, "zlib": vtk.vtkZLibDataCompressor, "lz4": vtk.vtkLZ4DataCompressor,
                   "lzma": vtk.vtkLZMADataCompressor}
    variants = [("ascii", "none", 32), ("binary", "zlib", 32), ("binary", "none", 64),
                ("appended_raw", "lz4", 64), ("appended_raw", "zlib", 64), ("appended_base64", "lzma", 32),
                ("appended_base64", "none", 64)]
    for mode, compressor, header in variants:
        w = vtk.vtkXMLUnstructuredGridWriter()
        w.SetInputData(g)
        w.SetFileName(os.path.join(HERE, "xml_%s_%s_h%d.vtu" % (mode, compressor, header)))
        if mode == "ascii":
            w.SetDataModeToAscii()
        elif mode == "binary":
            w.SetDataModeToBinary()
        else:
            w.SetDataModeToAppended()
            w.SetEncodeAppendedData(mode == "appended_base64")
        if compressors[compressor] is None:
            w.SetCompressorTypeToNone()
        else:
            w.SetCompressor(compressors[compressor]())
        w.SetHeaderType(w.UInt64 if header == 64 else w.UInt32)
        w.SetBlockSize(64)
        w.Write()


if __name__ == "__main__":
    main()
