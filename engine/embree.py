"""Embree 4 called from the engine's own kernels: scenes built through its C API, rays traced by
``@njit`` loops that call ``rtcIntersect4`` / ``rtcOccluded4`` directly.

Why not the ``embreex`` Python binding's ``EmbreeScene.run``: it traces one ray at a time
through a Cython loop that builds its output arrays on every call. These kernels trace packets of
4 and take 1.2-1.8x less CPU time per coherent ray and 0.9-1.4x per incoherent one, with the same
results (``bench/embree_binding.py``, table in docs/performance.md). A batch from the main thread
is split over the cores in plain threads (the kernels release the GIL), which made an LDC bake
1.27x faster; the reference renderer, whose pipelines already kept both cores busy, is unchanged.
The library is the one the ``embreex`` wheel ships (``embreex.libs/libembree4-*.so``), so the
dependency stays one pip package.

How a kernel reaches Embree: llvmlite loads the library into the process's symbol table
(``load_library_permanently``) and the kernels declare ``rtcIntersect4`` / ``rtcOccluded4`` as
external functions by name, so the machine code numba caches on disk holds a symbol, not an
address, and a cached kernel links against the library in any process.

Layout (Embree 4's ``rtcore_ray.h``, structure of arrays, 16-byte aligned): a packet of 4 rays is
12 x 4 words (``org_x .. org_z, tnear, dir_x .. dir_z, time, tfar, mask, id, flags``); a ray-hit
packet appends 9 x 4 words (``Ng_x .. Ng_z, u, v, primID, geomID, instID[1], instPrimID[1]``).
A miss leaves ``geomID`` invalid; an occluded ray gets ``tfar = -inf``.

Public API: :func:`build_scene` (a :class:`Scene` handle, released when unreferenced),
:func:`intersect`, :func:`occluded`.
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading
import weakref

import llvmlite.binding as llvm
import numba as nb
import numpy as np
from numba import types as nbt

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import EngineError
from engine.sched import run_pieces_parallel

W = 4  # rays per packet: measured fastest of 1, 4, 8 and 16 on this engine's incoherent batches
_RAY_WORDS = 12 * W
_RAYHIT_WORDS = 21 * W
_INVALID = np.uint32(0xFFFFFFFF)
_MIN_PIECE = 4096  # fewer rays than this per piece cost more in dispatch than they save

# Embree 4 enums (rtcore_geometry.h, rtcore_buffer.h, rtcore_common.h)
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX = 0
_BUFFER_TYPE_VERTEX = 1
_FORMAT_UINT3 = 0x5003
_FORMAT_FLOAT3 = 0x9003
_SCENE_FLAG_ROBUST = 1 << 2


def _library_path() -> str:
    import embreex

    libs = os.path.join(os.path.dirname(os.path.dirname(embreex.__file__)), "embreex.libs")
    found = sorted(glob.glob(os.path.join(libs, "libembree4*.so*")))
    if not found:
        raise EngineError(f"Embree 4 library not found in {libs} (the embreex wheel ships it)")
    return found[0]


def _load() -> ctypes.CDLL:
    path = _library_path()
    lib = ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
    llvm.load_library_permanently(path)  # so the kernels' external symbols resolve
    vp = ctypes.c_void_p
    lib.rtcNewDevice.restype = vp
    lib.rtcNewDevice.argtypes = [ctypes.c_char_p]
    lib.rtcGetDeviceError.restype = ctypes.c_int
    lib.rtcGetDeviceError.argtypes = [vp]
    lib.rtcNewScene.restype = vp
    lib.rtcNewScene.argtypes = [vp]
    lib.rtcNewGeometry.restype = vp
    lib.rtcNewGeometry.argtypes = [vp, ctypes.c_int]
    lib.rtcSetNewGeometryBuffer.restype = vp
    lib.rtcSetNewGeometryBuffer.argtypes = [vp, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t,
                                            ctypes.c_size_t]
    for name in ("rtcCommitGeometry", "rtcReleaseGeometry", "rtcCommitScene", "rtcReleaseScene"):
        getattr(lib, name).argtypes = [vp]
        getattr(lib, name).restype = None
    lib.rtcSetSceneFlags.argtypes = [vp, ctypes.c_int]
    lib.rtcSetSceneFlags.restype = None
    lib.rtcAttachGeometry.argtypes = [vp, vp]
    lib.rtcAttachGeometry.restype = ctypes.c_uint
    return lib


_LIB = _load()
_DEVICE: int | None = None
_DEVICE_LOCK = threading.Lock()


def _device() -> int:
    """The process's Embree device, created on first use (never before a fork: see
    workers/jobs/bake.py, ``preload_modules``)."""
    global _DEVICE
    with _DEVICE_LOCK:
        if _DEVICE is None:
            dev = _LIB.rtcNewDevice(None)
            if not dev:
                raise EngineError("Embree could not create a device")
            _DEVICE = int(dev)
        return _DEVICE


class Scene:
    """A committed Embree scene of one triangle mesh; ``ptr`` is what the kernels take. Released
    when the last reference goes."""

    def __init__(self, ptr: int, n_triangles: int):
        self.ptr = np.uint64(ptr)
        self.n_triangles = n_triangles
        self.release = weakref.finalize(self, _LIB.rtcReleaseScene, ctypes.c_void_p(ptr))


def build_scene(tri_local32: np.ndarray) -> Scene:
    """An Embree scene of triangles (nt, 3, 3) float32 (corners relative to the scene's centre)."""
    tri = np.ascontiguousarray(tri_local32, dtype=np.float32)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3) or tri.shape[0] == 0:
        raise EngineError(f"an Embree scene needs (n > 0, 3, 3) triangles, got {tri.shape}")
    nt = tri.shape[0]
    dev = ctypes.c_void_p(_device())
    scene = _LIB.rtcNewScene(dev)
    geom = _LIB.rtcNewGeometry(dev, _GEOMETRY_TYPE_TRIANGLE)
    if scene:
        _LIB.rtcSetSceneFlags(scene, _SCENE_FLAG_ROBUST)
    if not scene or not geom:
        raise EngineError(f"Embree could not create a scene (error {_LIB.rtcGetDeviceError(dev)})")
    # Embree reads vertex buffers with 16-byte loads: one spare vertex keeps the last load inside
    vb = _LIB.rtcSetNewGeometryBuffer(geom, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3, 12, 3 * nt + 1)
    ib = _LIB.rtcSetNewGeometryBuffer(geom, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3, 12, nt)
    if not vb or not ib:
        raise EngineError(f"Embree could not allocate {nt} triangles (error {_LIB.rtcGetDeviceError(dev)})")
    ctypes.memmove(vb, tri.ctypes.data, tri.nbytes)
    idx = np.arange(3 * nt, dtype=np.uint32)
    ctypes.memmove(ib, idx.ctypes.data, idx.nbytes)
    _LIB.rtcCommitGeometry(geom)
    _LIB.rtcAttachGeometry(scene, geom)
    _LIB.rtcReleaseGeometry(geom)
    _LIB.rtcCommitScene(scene)
    err = _LIB.rtcGetDeviceError(dev)
    if err:
        _LIB.rtcReleaseScene(scene)
        raise EngineError(f"Embree failed to build a scene of {nt} triangles (error {err})")
    return Scene(int(scene), nt)


_intersect4 = nbt.ExternalFunction("rtcIntersect4", nbt.void(nbt.uint64, nbt.uint64, nbt.uint64, nbt.uint64))
_occluded4 = nbt.ExternalFunction("rtcOccluded4", nbt.void(nbt.uint64, nbt.uint64, nbt.uint64, nbt.uint64))


@nb.njit(cache=True, inline="always")
def _packet(n_words):
    """A packet buffer of ``n_words`` float32 words on a 64-byte boundary, its uint32 view and the
    packet's lane mask: (buf, ib, valid)."""
    raw = np.empty(n_words + 16, np.float32)
    off = ((raw.ctypes.data + 63) // 64 * 64 - raw.ctypes.data) // 4
    buf = raw[off:off + n_words]
    return buf, buf.view(np.uint32), np.empty(W, np.int32)


@nb.njit(cache=True, inline="always")
def _set_valid(valid, k):
    """Lanes 0 .. k - 1 of the packet are traced, the rest are not."""
    for j in range(W):
        valid[j] = -1 if j < k else 0


@nb.njit(cache=True, inline="always")
def _load_rays(buf, ib, o, d, tfar, a, k):
    """Rays a .. a + k - 1 (k <= W) into the packet's ray part; the unused lanes repeat ray a."""
    for j in range(W):
        i = a + (j if j < k else 0)
        buf[j] = o[i, 0]
        buf[W + j] = o[i, 1]
        buf[2 * W + j] = o[i, 2]
        buf[3 * W + j] = 0.0
        buf[4 * W + j] = d[i, 0]
        buf[5 * W + j] = d[i, 1]
        buf[6 * W + j] = d[i, 2]
        buf[7 * W + j] = 0.0
        buf[8 * W + j] = tfar[i] if tfar.shape[0] else np.inf
        ib[9 * W + j] = _INVALID  # mask: every geometry
        ib[10 * W + j] = 0
        ib[11 * W + j] = 0


@nb.njit(cache=True, nogil=True)
def _intersect_kernel(scene, o, d, lo, hi, prim, u, v, t):
    """First hits of rays lo .. hi - 1, in packets of W."""
    no_tfar = np.empty(0, np.float32)
    buf, ib, valid = _packet(_RAYHIT_WORDS)
    for a in range(lo, hi, W):
        k = min(W, hi - a)
        _set_valid(valid, k)
        for j in range(W):
            ib[18 * W + j] = _INVALID  # geomID
            ib[19 * W + j] = _INVALID  # instID[0]
        _load_rays(buf, ib, o, d, no_tfar, a, k)
        _intersect4(valid.ctypes.data, scene, buf.ctypes.data, 0)
        for j in range(k):
            i = a + j
            if ib[18 * W + j] == _INVALID:
                prim[i] = -1
                u[i] = 0.0
                v[i] = 0.0
                t[i] = np.inf
            else:
                prim[i] = np.int32(ib[17 * W + j])
                u[i] = buf[15 * W + j]
                v[i] = buf[16 * W + j]
                t[i] = buf[8 * W + j]


@nb.njit(cache=True, nogil=True)
def _occluded_kernel(scene, o, d, tmax, lo, hi, occ):
    """Occlusion of rays lo .. hi - 1 up to ``tmax``, in packets of W."""
    buf, ib, valid = _packet(_RAY_WORDS)
    for a in range(lo, hi, W):
        k = min(W, hi - a)
        _set_valid(valid, k)
        _load_rays(buf, ib, o, d, tmax, a, k)
        _occluded4(valid.ctypes.data, scene, buf.ctypes.data, 0)
        for j in range(k):
            occ[a + j] = buf[8 * W + j] < 0.0


def intersect(scene: Scene, o32: np.ndarray, d32: np.ndarray, serial: bool | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """First hits of float32 rays (n, 3) relative to the scene's centre: (prim int32, -1 on a miss;
    u, v, t float32, t = inf on a miss). ``serial``: one thread (None: parallel from the main
    thread only)."""
    n = o32.shape[0]
    prim = np.empty(n, np.int32)
    u = np.empty(n, np.float32)
    v = np.empty(n, np.float32)
    t = np.empty(n, np.float32)
    if n:
        o = np.ascontiguousarray(o32, dtype=np.float32)
        d = np.ascontiguousarray(d32, dtype=np.float32)
        run_pieces_parallel(lambda lo, hi: _intersect_kernel(scene.ptr, o, d, lo, hi, prim, u, v, t), n, _MIN_PIECE,
                            serial)
    return prim, u, v, t


def occluded(scene: Scene, o32: np.ndarray, d32: np.ndarray, tmax32: np.ndarray, serial: bool | None = None
             ) -> np.ndarray:
    """(n,) bool: something lies strictly between each float32 origin and ``tmax32`` along its
    direction. ``serial`` as in :func:`intersect`."""
    n = o32.shape[0]
    occ = np.empty(n, np.bool_)
    if n:
        o = np.ascontiguousarray(o32, dtype=np.float32)
        d = np.ascontiguousarray(d32, dtype=np.float32)
        tm = np.ascontiguousarray(tmax32, dtype=np.float32)
        run_pieces_parallel(lambda lo, hi: _occluded_kernel(scene.ptr, o, d, tm, lo, hi, occ), n, _MIN_PIECE, serial)
    return occ


__all__ = ["Scene", "build_scene", "intersect", "occluded"]
