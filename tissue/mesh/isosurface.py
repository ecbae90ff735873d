"""The zero level of a function sampled on a regular grid, as a triangle surface: VTK's marching
cubes, its largest component, windowed-sinc (Taubin) smoothing and quadric decimation.

VTK's filters are called directly, with the settings pyvista's `contour(method="marching_cubes")`,
`triangulate`, `clean`, `connectivity("largest")`, `smooth_taubin` and `decimate` give them: a run
that makes an organ's surface then imports a few of VTK's modules rather than pyvista, and the
surface is the same (tests/test_organs.py compares the two bit for bit). pyvista's
`connectivity("largest")` also runs the filter a second time over the largest region to relabel it;
that pass keeps the cells' order, so the cleaned surface after it is the same without it.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkImageData, vtkPolyData
from vtkmodules.vtkFiltersCore import (vtkCleanPolyData, vtkConnectivityFilter, vtkMarchingCubes,
                                       vtkQuadricDecimation, vtkTriangleFilter,
                                       vtkWindowedSincPolyDataFilter)


def sampling_grid(lo, dims, spacing: float) -> tuple[vtkImageData, np.ndarray]:
    """A grid of dims points from lo, `spacing` apart, and its points ((n, 3), x running fastest)."""
    grid = vtkImageData()
    grid.SetDimensions(*(int(d) for d in dims))
    grid.SetSpacing(spacing, spacing, spacing)
    grid.SetOrigin(*(float(x) for x in lo))
    return grid, vtk_to_numpy(grid.GetPoints().GetData())


def smoothed_zero_level(grid: vtkImageData, values: np.ndarray, smooth_iterations: int,
                        pass_band: float) -> vtkPolyData:
    """The largest component of the zero level of `values` (one per grid point), smoothed."""
    array = numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64))
    array.SetName("f")
    grid.GetPointData().AddArray(array)
    contour = vtkMarchingCubes()
    contour.SetComputeNormals(False)
    contour.SetComputeGradients(False)
    contour.SetComputeScalars(True)
    contour.SetInputArrayToProcess(0, 0, 0, vtkDataObject.FIELD_ASSOCIATION_POINTS, "f")
    contour.SetNumberOfContours(1)
    contour.SetValue(0, 0.0)
    surface = _clean(_triangles(_run(contour, grid)))
    largest = vtkConnectivityFilter()
    largest.ColorRegionsOn()
    largest.SetRegionIdAssignmentMode(largest.CELL_COUNT_DESCENDING)
    largest.SetExtractionModeToLargestRegion()
    surface = _clean(_run(largest, surface))
    smooth = vtkWindowedSincPolyDataFilter()
    smooth.SetNumberOfIterations(smooth_iterations)
    smooth.SetFeatureEdgeSmoothing(False)
    smooth.SetNonManifoldSmoothing(False)
    smooth.SetFeatureAngle(45.0)
    smooth.SetEdgeAngle(15.0)
    smooth.SetBoundarySmoothing(True)
    smooth.SetPassBand(pass_band)
    smooth.SetNormalizeCoordinates(False)
    smooth.SetWindowFunctionToNuttall()
    return _run(smooth, surface)


def decimated(surface: vtkPolyData, reduction: float) -> vtkPolyData:
    """The surface with `reduction` of its triangles collapsed away, volume preserved."""
    decimate = vtkQuadricDecimation()
    decimate.SetVolumePreservation(True)
    decimate.SetAttributeErrorMetric(False)
    decimate.SetTargetReduction(reduction)
    decimate.SetWeighBoundaryConstraintsByLength(False)
    decimate.SetBoundaryWeightFactor(1.0)
    return _clean(_triangles(_run(decimate, surface)))


def surface_arrays(surface: vtkPolyData) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) float64, triangles (m, 3) int64) of a surface of triangles."""
    points = vtk_to_numpy(surface.GetPoints().GetData()).astype(np.float64)
    triangles = vtk_to_numpy(surface.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
    return points, triangles


def _run(algorithm, data):
    algorithm.SetInputData(data)
    algorithm.Update()
    return algorithm.GetOutput()


def _triangles(data: vtkPolyData) -> vtkPolyData:
    split = vtkTriangleFilter()
    split.SetPassVerts(False)
    split.SetPassLines(False)
    return _run(split, data)


def _clean(data: vtkPolyData) -> vtkPolyData:
    """Coincident points merged, unused ones dropped (pyvista's `clean()` defaults)."""
    clean = vtkCleanPolyData()
    clean.SetPointMerging(True)
    clean.SetConvertLinesToPoints(True)
    clean.SetConvertPolysToLines(True)
    clean.SetConvertStripsToPolys(True)
    return _run(clean, data)
