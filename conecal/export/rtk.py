"""RTK geometry (XML) and FDK reconstruction through itk-rtk (optional).

itk-rtk is an extra, not a core dependency: ``pip install 'conecal[rtk]'``.
RTK describes each view by a source position, a detector position and the
detector's row and column directions (``AddProjection``); its projection
images carry the pixel pitch as spacing and an origin that puts physical
(0, 0) at the detector centre, pixel coordinates ((cols-1)/2, (rows-1)/2).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import ConeGeometry
from ..jsonio import atomic_write


def _rtk():
    try:
        import itk
        from itk import RTK
    except ImportError:  # pragma: no cover - depends on the environment
        raise InputError("RTK export and FDK need itk-rtk: pip install 'conecal[rtk]'") from None
    return itk, RTK


def rtk_geometry(views: list[ConeGeometry]):
    """An ``rtk.ThreeDCircularProjectionGeometry`` with one projection per view."""
    itk, rtk = _rtk()
    geo = rtk.ThreeDCircularProjectionGeometry.New()
    P = itk.Point[itk.D, 3]
    V = itk.Vector[itk.D, 3]
    for k, g in enumerate(views):
        ok = geo.AddProjection(P(list(map(float, g.source))), P(list(map(float, g.detector_centre))),
                               V(list(map(float, g.u))), V(list(map(float, g.v))))
        if not ok:
            raise InputError(f"view {k}: RTK refused the geometry (detector directions not orthonormal?)")
    return geo


def detector_origin_spacing(g: ConeGeometry):
    """RTK projection-image origin and spacing (x = column, y = row), mm."""
    rows, cols = g.shape
    pu, pv = g.pixel_pitch
    return (-(cols - 1) / 2 * pu, -(rows - 1) / 2 * pv), (pu, pv)


def rtk_matrices(geo, g: ConeGeometry) -> np.ndarray:
    """RTK's own 3x4 projection matrices, converted to pixel coordinates
    (column, row, 1) like conecal's, normalised to P[2, 3] = 1 where possible."""
    itk, _ = _rtk()
    (ox, oy), (pu, pv) = detector_origin_spacing(g)
    A = np.array([[1 / pu, 0, -ox / pu], [0, 1 / pv, -oy / pv], [0, 0, 1]])
    out = []
    for k in range(len(geo.GetGantryAngles())):
        M = np.asarray(itk.array_from_matrix(geo.GetMatrix(k)), float)
        out.append(A @ M)
    return np.array(out)


def write_rtk_xml(path, views: list[ConeGeometry]) -> Path:
    """RTK geometry XML of ``views``, written atomically."""
    _, rtk = _rtk()
    path = Path(path)
    geo = rtk_geometry(views)

    def write(fh):   # RTK writes to a file name: render in a scratch folder, then one atomic write
        with tempfile.TemporaryDirectory() as d:
            w = rtk.ThreeDCircularProjectionGeometryXMLFileWriter.New()
            w.SetFilename(str(Path(d) / "geometry.xml"))
            w.SetObject(geo)
            w.WriteFile()
            fh.write((Path(d) / "geometry.xml").read_bytes())

    atomic_write(path, write)
    return path


def read_rtk_xml(path):
    """The RTK geometry object of an RTK geometry XML file."""
    _, rtk = _rtk()
    r = rtk.ThreeDCircularProjectionGeometryXMLFileReader.New()
    r.SetFilename(str(path))
    r.GenerateOutputInformation()
    return r.GetOutputObject()


def fdk(projections: np.ndarray, views: list[ConeGeometry], *, size, spacing, origin=None,
        hann_cut: float = 0.0) -> np.ndarray:
    """FDK reconstruction (itk-rtk, CPU) of ``projections`` (n_views, rows,
    cols; attenuation) on a grid of ``size`` (nx, ny, nz) voxels of
    ``spacing`` mm centred on the sample origin. Returns (nz, ny, nx)."""
    itk, rtk = _rtk()
    g0 = views[0]
    (ox, oy), (pu, pv) = detector_origin_spacing(g0)
    proj = itk.image_from_array(np.ascontiguousarray(projections, dtype=np.float32))
    proj.SetSpacing([float(pu), float(pv), 1.0])
    proj.SetOrigin([float(ox), float(oy), 0.0])
    size = [int(x) for x in size]
    spacing = [float(x) for x in (spacing if np.ndim(spacing) else (spacing,) * 3)]
    if origin is None:
        origin = [-(n - 1) / 2 * s for n, s in zip(size, spacing)]
    ImageType = itk.Image[itk.F, 3]
    const = rtk.ConstantImageSource[ImageType].New()
    const.SetOrigin([float(x) for x in origin])
    const.SetSpacing(spacing)
    const.SetSize(size)
    const.SetConstant(0.0)
    f = rtk.FDKConeBeamReconstructionFilter[ImageType].New()
    f.SetInput(0, const.GetOutput())
    f.SetInput(1, proj)
    f.SetGeometry(rtk_geometry(views))
    f.GetRampFilter().SetHannCutFrequency(hann_cut)
    f.Update()
    return np.asarray(itk.array_from_image(f.GetOutput())).copy()


def fdk_scan(scan, geometries: list[ConeGeometry], *, step: int = 1, size, spacing, origin=None) -> list[np.ndarray]:
    """FDK of a scan's frames (every ``step``-th) with each lab geometry in
    ``geometries`` and the scan's nominal motion; the frames are read once."""
    from . import per_view

    idx = np.arange(0, scan.n_frames, step)
    stack = np.stack([scan.stack.read(int(scan.log.frame[k])) for k in idx])
    T = scan.nominal_transforms()[idx]
    return [fdk(stack, per_view(g, T), size=size, spacing=spacing, origin=origin) for g in geometries]


def sharpness(volume: np.ndarray) -> float:
    """Gradient energy over signal energy of a reconstruction (1/voxel^2):
    doubled or smeared edges lower it."""
    v = np.asarray(volume, float)
    grads = np.gradient(v, axis=(-1, -2))
    num = sum(float(np.sum(gr**2)) for gr in grads)
    den = float(np.sum((v - v.mean()) ** 2)) or 1.0
    return num / den
