"""glTF 2.0 (``.gltf`` with its buffers, ``.glb``) -> the project's scene document and mesh blobs.

A strict reader of the parts the project can use (docs/scene-import.md): buffers, buffer views and
accessors are parsed here with numpy, every offset, count and index checked against what holds it
before a byte is read; errors name the glTF part (``accessors[3].count``). Nothing is fetched: a
buffer is a data: URI, the GLB's binary chunk, or another file part of the same upload.
"""

from __future__ import annotations

import base64
import json
import math
import struct
import urllib.parse
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from api_schemas.scene import MAX_MESH_FACES
from producer.scene_import.common import (
    ImportOptions,
    MeshData,
    SceneBuilder,
    Warnings,
    companion_uri_problem,
    fail,
    pbr_material,
    resolution,
    safe_name,
)

__all__ = ["import_gltf", "gltf_companions"]

_COMPONENTS: dict[int, tuple[str, str]] = {
    5120: ("<i1", "BYTE"), 5121: ("<u1", "UNSIGNED_BYTE"), 5122: ("<i2", "SHORT"),
    5123: ("<u2", "UNSIGNED_SHORT"), 5125: ("<u4", "UNSIGNED_INT"), 5126: ("<f4", "FLOAT"),
}
_TYPES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_INDEX_TYPES = (5121, 5123, 5125)
_GLB_JSON = 0x4E4F534A
_GLB_BIN = 0x004E4942
_MAX_ITEMS = 1_000_000  # entries of any top-level array: far beyond a real file, bounds the work
_MAX_ELEMENTS = 3 * MAX_MESH_FACES  # the most elements any accessor the importer reads can need

SUPPORTED_EXTENSIONS = frozenset({
    "KHR_lights_punctual", "KHR_materials_specular", "KHR_materials_emissive_strength", "KHR_materials_ior",
})


# --------------------------------------------------------------------------- JSON accessors


def _where(*parts: str | int) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else p)
    return out


def _dict(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise fail(where, f"must be a JSON object, got {type(value).__name__}")
    return value


def _list(doc: Mapping[str, Any], key: str, where: str) -> list[Any]:
    value = doc.get(key, [])
    if not isinstance(value, list):
        raise fail(where, f"must be a JSON array, got {type(value).__name__}")
    if len(value) > _MAX_ITEMS:
        raise fail(where, f"{len(value)} entries, more than the {_MAX_ITEMS} this importer reads")
    return value


def _int(value: Any, where: str, lo: int = 0, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        if isinstance(value, float) and value.is_integer() and math.isfinite(value):
            value = int(value)
        else:
            raise fail(where, f"must be an integer, got {value!r}"[:200])
    if value < lo or (hi is not None and value > hi):
        raise fail(where, f"{value} is out of range [{lo}, {hi if hi is not None else 'inf'}]")
    return int(value)


def _num(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise fail(where, f"must be a number, got {value!r}"[:200])
    x = float(value)
    if not math.isfinite(x):
        raise fail(where, f"must be finite, got {value!r}")
    return x


def _nums(value: Any, n: int, where: str) -> list[float]:
    if not isinstance(value, list) or len(value) != n:
        raise fail(where, f"must be an array of {n} numbers")
    return [_num(v, f"{where}[{i}]") for i, v in enumerate(value)]


def _ref(value: Any, items: list[Any], where: str, what: str) -> int:
    i = _int(value, where)
    if i >= len(items):
        raise fail(where, f"refers to {what}[{i}], but the file has {len(items)}")
    return i


# --------------------------------------------------------------------------- containers


def _parse_glb(data: bytes) -> tuple[bytes, bytes | None]:
    if len(data) < 12:
        raise fail("glb", f"{len(data)} bytes: shorter than the 12-byte GLB header")
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF":
        raise fail("glb", "not a GLB file: missing the 'glTF' magic")
    if version != 2:
        raise fail("glb", f"GLB version {version}; only version 2 is supported")
    if length != len(data):
        raise fail("glb", f"the header declares {length} bytes, the file has {len(data)} (truncated?)")
    chunks: list[tuple[int, bytes]] = []
    offset = 12
    while offset < len(data):
        if offset + 8 > len(data):
            raise fail(f"glb chunk {len(chunks)}", "truncated chunk header")
        clen, ctype = struct.unpack_from("<II", data, offset)
        if offset + 8 + clen > len(data):
            raise fail(f"glb chunk {len(chunks)}",
                       f"declares {clen} bytes, only {len(data) - offset - 8} remain in the file")
        chunks.append((ctype, data[offset + 8: offset + 8 + clen]))
        offset += 8 + clen
    if not chunks or chunks[0][0] != _GLB_JSON:
        raise fail("glb chunk 0", "the first chunk must be the JSON chunk")
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == _GLB_BIN else None
    return chunks[0][1], binary


def _load_json(raw: bytes, where: str) -> dict[str, Any]:
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    try:
        doc = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise fail(where, f"not UTF-8 text ({exc})") from None
    except (ValueError, RecursionError) as exc:
        raise fail(where, f"not a glTF file: invalid JSON ({exc})") from None
    return _dict(doc, where)


def gltf_companions(raw: bytes, images: bool = False) -> list[str]:
    """The relative buffer URIs a ``.gltf`` needs from its upload (for a client to send them); with
    ``images``, its relative image URIs too (files it names that the import does not read)."""
    try:
        doc = json.loads(raw.decode("utf-8-sig"))
    except (ValueError, RecursionError):
        return []
    out: list[str] = []
    for key in ("buffers", "images") if images else ("buffers",):
        items = doc.get(key) if isinstance(doc, dict) else None
        for item in items if isinstance(items, list) else []:
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:") and companion_uri_problem(uri) is None:
                out.append(urllib.parse.unquote(uri))
    return out


def _data_uri(uri: str, where: str) -> bytes:
    head, sep, payload = uri.partition(",")
    if not sep or not head.endswith(";base64"):
        raise fail(where, "a data: URI must be base64 (data:<type>;base64,...)")
    try:
        return base64.b64decode(payload, validate=True)
    except ValueError as exc:
        raise fail(where, f"invalid base64 data ({exc})") from None


# --------------------------------------------------------------------------- the reader


class _Gltf:
    def __init__(self, doc: dict[str, Any], binary: bytes | None, files: Mapping[str, bytes],
                 warnings: Warnings) -> None:
        self.doc = doc
        self.warnings = warnings
        self.buffers = self._buffers(binary, files)
        self.views = self._views()
        self.accessors = _list(doc, "accessors", "accessors")
        self._accessor_cache: dict[int, np.ndarray] = {}
        for i in range(len(self.accessors)):
            self._check_accessor(i)

    def _buffers(self, binary: bytes | None, files: Mapping[str, bytes]) -> list[bytes]:
        out: list[bytes] = []
        for i, raw in enumerate(_list(self.doc, "buffers", "buffers")):
            b = _dict(raw, f"buffers[{i}]")
            length = _int(b.get("byteLength"), f"buffers[{i}].byteLength", 1)
            uri = b.get("uri")
            if uri is None:
                if i != 0 or binary is None:
                    raise fail(f"buffers[{i}]", "has no uri, and only buffers[0] of a .glb may use the binary chunk"
                               + ("" if binary is not None else " (this file has none)"))
                data = binary
            elif not isinstance(uri, str):
                raise fail(f"buffers[{i}].uri", "must be a string")
            elif uri.startswith("data:"):
                data = _data_uri(uri, f"buffers[{i}].uri")
            else:
                problem = companion_uri_problem(uri)
                if problem is not None:
                    raise fail(f"buffers[{i}].uri", problem)
                name = urllib.parse.unquote(uri)
                if name not in files:
                    raise fail(f"buffers[{i}].uri", f"the buffer file {name!r} is missing: upload it as a file "
                                                   "part of that name (or send a .glb)")
                data = files[name]
            if len(data) < length:
                raise fail(f"buffers[{i}].byteLength", f"declares {length} bytes, the data has {len(data)}")
            out.append(data[:length])
        return out

    def _views(self) -> list[tuple[int, int, int, int | None]]:
        out: list[tuple[int, int, int, int | None]] = []
        for i, raw in enumerate(_list(self.doc, "bufferViews", "bufferViews")):
            w = f"bufferViews[{i}]"
            v = _dict(raw, w)
            buf = _ref(v.get("buffer"), self.buffers, f"{w}.buffer", "buffers")
            offset = _int(v.get("byteOffset", 0), f"{w}.byteOffset")
            length = _int(v.get("byteLength"), f"{w}.byteLength", 1)
            if offset + length > len(self.buffers[buf]):
                raise fail(f"{w}.byteLength", f"bytes {offset}..{offset + length} run past the end of "
                                              f"buffers[{buf}] ({len(self.buffers[buf])} bytes)")
            stride = v.get("byteStride")
            if stride is not None:
                stride = _int(stride, f"{w}.byteStride", 4, 252)
                if stride % 4:
                    raise fail(f"{w}.byteStride", f"{stride} is not a multiple of 4")
            out.append((buf, offset, length, stride))
        return out

    def _check_accessor(self, i: int) -> None:
        w = f"accessors[{i}]"
        a = _dict(self.accessors[i], w)
        ctype = _int(a.get("componentType"), f"{w}.componentType")
        if ctype not in _COMPONENTS:
            raise fail(f"{w}.componentType", f"{ctype} is not a glTF component type "
                                             f"({', '.join(str(k) for k in _COMPONENTS)})")
        kind = a.get("type")
        if not isinstance(kind, str) or kind not in _TYPES:
            raise fail(f"{w}.type", f"{kind!r} is not a glTF accessor type ({', '.join(_TYPES)})"[:200])
        count = _int(a.get("count"), f"{w}.count", 1)
        if count > _MAX_ELEMENTS:
            raise fail(f"{w}.count", f"{count} elements: more than the {_MAX_ELEMENTS} any use of an accessor "
                                     f"allows ({MAX_MESH_FACES} triangles of 3 indices)")
        size = np.dtype(_COMPONENTS[ctype][0]).itemsize
        elem = size * _TYPES[kind]
        offset = _int(a.get("byteOffset", 0), f"{w}.byteOffset")
        if offset % size:
            raise fail(f"{w}.byteOffset", f"{offset} is not a multiple of the component size {size}")
        if kind.startswith("MAT") and ctype != 5126:
            raise fail(f"{w}.componentType", "matrix accessors of integer components are not read")
        if "bufferView" in a:
            view = _ref(a["bufferView"], self.views, f"{w}.bufferView", "bufferViews")
            _, _, vlen, stride = self.views[view]
            step = stride or elem
            if stride is not None and stride < elem:
                raise fail(f"bufferViews[{view}].byteStride",
                           f"{stride} is smaller than one element of accessors[{i}] ({elem} bytes)")
            if offset + elem > vlen:
                raise fail(f"{w}.byteOffset", f"{offset}: one element of {elem} bytes from there runs past "
                                              f"bufferViews[{view}] ({vlen} bytes)")
            need = offset + step * (count - 1) + elem
            if need > vlen:
                raise fail(f"{w}.count", f"{count} elements of {elem} bytes (stride {step}) from byteOffset "
                                         f"{offset} need {need} bytes; bufferViews[{view}] has {vlen}")
        elif "sparse" not in a:
            self.warnings.add("accessor_without_data", w, "an accessor without bufferView or sparse data "
                                                          "reads as zeros (as the glTF specification says)")
        if "sparse" in a:
            s = _dict(a["sparse"], f"{w}.sparse")
            scount = _int(s.get("count"), f"{w}.sparse.count", 1, count)
            idx = _dict(s.get("indices"), f"{w}.sparse.indices")
            ictype = _int(idx.get("componentType"), f"{w}.sparse.indices.componentType")
            if ictype not in _INDEX_TYPES:
                raise fail(f"{w}.sparse.indices.componentType", f"{ictype} is not an unsigned integer type")
            self._span(idx, scount * np.dtype(_COMPONENTS[ictype][0]).itemsize, f"{w}.sparse.indices")
            vals = _dict(s.get("values"), f"{w}.sparse.values")
            self._span(vals, scount * elem, f"{w}.sparse.values")

    def _span(self, part: dict[str, Any], nbytes: int, where: str) -> tuple[int, int]:
        view = _ref(part.get("bufferView"), self.views, f"{where}.bufferView", "bufferViews")
        offset = _int(part.get("byteOffset", 0), f"{where}.byteOffset")
        if self.views[view][3] is not None:
            raise fail(f"{where}.bufferView", "sparse data must be tightly packed (no byteStride)")
        if offset + nbytes > self.views[view][2]:
            raise fail(f"{where}.byteOffset", f"{nbytes} bytes from {offset} run past bufferViews[{view}] "
                                              f"({self.views[view][2]} bytes)")
        return view, offset

    def _view_bytes(self, view: int) -> memoryview:
        buf, offset, length, _ = self.views[view]
        return memoryview(self.buffers[buf])[offset: offset + length]

    def read(self, i: int, use: str, types: tuple[str, ...], components: tuple[int, ...]) -> np.ndarray:
        """Accessor i as a (count, n) array of its component type (already bounds-checked)."""
        w = f"accessors[{i}]"
        a = self.accessors[i]
        if a["type"] not in types:
            raise fail(f"{w}.type", f"{use} needs {' or '.join(types)}, the accessor is {a['type']}")
        ctype = int(a["componentType"])
        if ctype not in components:
            names = ", ".join(f"{_COMPONENTS[c][1]} ({c})" for c in components)
            raise fail(f"{w}.componentType", f"{use} needs {names}; the accessor is "
                                             f"{_COMPONENTS[ctype][1]} ({ctype})")
        if i in self._accessor_cache:
            return self._accessor_cache[i]
        dtype = np.dtype(_COMPONENTS[ctype][0])
        n = _TYPES[a["type"]]
        count = int(a["count"])
        offset = int(a.get("byteOffset", 0))
        if "bufferView" in a:
            view = int(a["bufferView"])
            stride = self.views[view][3] or dtype.itemsize * n
            raw = self._view_bytes(view)
            arr = np.ndarray(shape=(count, n), dtype=dtype, buffer=raw, offset=offset,
                             strides=(stride, dtype.itemsize)).copy()
        else:
            arr = np.zeros((count, n), dtype=dtype)
        if "sparse" in a:
            s = a["sparse"]
            scount = int(s["count"])
            idx_part, val_part = s["indices"], s["values"]
            idt = np.dtype(_COMPONENTS[int(idx_part["componentType"])][0])
            view, off = self._span(idx_part, scount * idt.itemsize, f"{w}.sparse.indices")
            idx = np.frombuffer(self._view_bytes(view), dtype=idt, count=scount, offset=off).astype(np.int64)
            if idx.max() >= count:
                raise fail(f"{w}.sparse.indices", f"index {int(idx.max())} is past the accessor's count {count}")
            if np.any(np.diff(idx) <= 0):
                raise fail(f"{w}.sparse.indices", "sparse indices must increase strictly")
            view, off = self._span(val_part, scount * dtype.itemsize * n, f"{w}.sparse.values")
            vals = np.frombuffer(self._view_bytes(view), dtype=dtype, count=scount * n, offset=off)
            arr[idx] = vals.reshape(scount, n)
        if dtype.kind == "f" and not np.all(np.isfinite(arr)):
            bad = int((~np.isfinite(arr)).any(axis=1).sum())
            raise fail(w, f"{use}: {bad} of {count} elements hold NaN or infinite values")
        self._accessor_cache[i] = arr
        return arr


# --------------------------------------------------------------------------- transforms


def _local_matrix(node: dict[str, Any], where: str) -> npt.NDArray[np.float64]:
    has_trs = [k for k in ("translation", "rotation", "scale") if k in node]
    if "matrix" in node:
        if has_trs:
            raise fail(f"{where}.matrix", f"a node with a matrix must not also have {', '.join(has_trs)}")
        m = np.array(_nums(node["matrix"], 16, f"{where}.matrix"), dtype=np.float64).reshape(4, 4).T
        if np.abs(m[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
            raise fail(f"{where}.matrix", "is not affine: its last row (elements 3, 7, 11, 15) must be 0, 0, 0, 1")
        m[3] = (0.0, 0.0, 0.0, 1.0)
        return m
    t = _nums(node.get("translation", [0, 0, 0]), 3, f"{where}.translation")
    q = _nums(node.get("rotation", [0, 0, 0, 1]), 4, f"{where}.rotation")
    s = _nums(node.get("scale", [1, 1, 1]), 3, f"{where}.scale")
    norm = math.sqrt(sum(c * c for c in q))
    if norm == 0:
        raise fail(f"{where}.rotation", "the quaternion is zero")
    x, y, z, w = (c / norm for c in q)
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    m = np.eye(4)
    m[:3, :3] = r * np.array(s)[None, :]
    m[:3, 3] = t
    return m


def _singular(m: npt.NDArray[np.float64]) -> bool:
    lin = m[:3, :3]
    col = np.abs(lin).max(axis=0)
    if np.any(col == 0):
        return True
    cols = lin / col
    return abs(float(np.linalg.det(cols))) / float(np.prod(np.linalg.norm(cols, axis=0))) < 1e-12


# --------------------------------------------------------------------------- conversion


_MATERIAL_EXTENSIONS_IGNORED_TEXTURES = {
    "KHR_materials_specular": ("specularTexture", "specularColorTexture"),
}
_TEXTURE_SLOTS = ("normalTexture", "occlusionTexture", "emissiveTexture")
_PBR_TEXTURES = ("baseColorTexture", "metallicRoughnessTexture")


def _clamp01(x: float) -> float:
    return min(max(x, 0.0), 1.0)


def _material(g: _Gltf, i: int, builder: SceneBuilder, emissive: dict[str, tuple[float, float, float]]) -> str:
    w = f"materials[{i}]"
    mat = _dict(g.doc["materials"][i], w)
    warn = g.warnings.add
    pbr = _dict(mat.get("pbrMetallicRoughness", {}), f"{w}.pbrMetallicRoughness")
    base4 = _nums(pbr.get("baseColorFactor", [1, 1, 1, 1]), 4, f"{w}.pbrMetallicRoughness.baseColorFactor")
    metallic = _num(pbr.get("metallicFactor", 1.0), f"{w}.pbrMetallicRoughness.metallicFactor")
    roughness = _num(pbr.get("roughnessFactor", 1.0), f"{w}.pbrMetallicRoughness.roughnessFactor")
    for slot in _PBR_TEXTURES:
        if slot in pbr:
            warn("textures", f"{w}.pbrMetallicRoughness.{slot}",
                 "textures are ignored: each material uses its constant factors alone")
    for slot in _TEXTURE_SLOTS:
        if slot in mat:
            warn("textures", f"{w}.{slot}", "textures are ignored: each material uses its constant factors alone")
    alpha_mode = mat.get("alphaMode", "OPAQUE")
    if alpha_mode != "OPAQUE" or base4[3] < 1:
        warn("transparency", f"{w}.alphaMode",
             "alpha (BLEND / MASK modes, baseColorFactor alpha) is ignored: surfaces are opaque")
    if not mat.get("doubleSided", False):
        warn("single_sided", f"{w}.doubleSided", "single-sided materials are rendered two-sided "
                                                  "(the project has no back-face culling)")
    emission = _nums(mat.get("emissiveFactor", [0, 0, 0]), 3, f"{w}.emissiveFactor")
    exts = _dict(mat.get("extensions", {}), f"{w}.extensions")
    strength = 1.0
    ior = 1.5
    spec_factor, spec_color = 1.0, [1.0, 1.0, 1.0]
    for name, ext_raw in exts.items():
        ew = f"{w}.extensions.{name}"
        ext = _dict(ext_raw, ew)
        if name == "KHR_materials_emissive_strength":
            strength = _num(ext.get("emissiveStrength", 1.0), f"{ew}.emissiveStrength")
            if strength < 0:
                raise fail(f"{ew}.emissiveStrength", f"must be >= 0, got {strength}")
        elif name == "KHR_materials_ior":
            ior = _num(ext.get("ior", 1.5), f"{ew}.ior")
            if ior != 0 and ior < 1:
                raise fail(f"{ew}.ior", f"must be 0 or >= 1, got {ior}")
        elif name == "KHR_materials_specular":
            spec_factor = _num(ext.get("specularFactor", 1.0), f"{ew}.specularFactor")
            spec_color = _nums(ext.get("specularColorFactor", [1, 1, 1]), 3, f"{ew}.specularColorFactor")
            for slot in _MATERIAL_EXTENSIONS_IGNORED_TEXTURES[name]:
                if slot in ext:
                    warn("textures", f"{ew}.{slot}", "textures are ignored: each material uses its constant "
                                                     "factors alone")
        else:
            warn("material_extension", ew, "material extensions other than KHR_materials_specular, "
                                           "KHR_materials_ior and KHR_materials_emissive_strength are ignored "
                                           "(transmission, clearcoat, sheen, volume, unlit, ...)")
    r0 = 1.0 if ior == 0 else ((ior - 1) / (ior + 1)) ** 2
    f0r, f0g, f0b = (min(r0 * max(c, 0.0), 1.0) * _clamp01(spec_factor) for c in spec_color)
    emit = tuple(max(0.0, e) * strength for e in emission)
    if "emissiveTexture" in mat and max(emit) > 0:
        # an emissive texture mostly masks where a surface glows; its factor alone would light the
        # whole surface, so the emission is left out instead
        warn("emissive_texture", f"{w}.emissiveTexture", "emission given by a texture is left out (the factor "
                                                          "alone would make the whole surface glow)")
        emit = (0.0, 0.0, 0.0)
    name = safe_name(mat.get("name"), f"material_{i}")
    doc = pbr_material(name, (base4[0], base4[1], base4[2]), metallic, roughness, (f0r, f0g, f0b),
                       (emit[0], emit[1], emit[2]))
    stored = builder.add_material(doc, w)
    if max(emit) > 0:
        emissive[stored] = (emit[0], emit[1], emit[2])
    return stored


def _triangles(mode: int, idx: npt.NDArray[np.int64], where: str) -> npt.NDArray[np.int64]:
    n = len(idx)
    if mode == 4:
        if n % 3:
            raise fail(where, f"TRIANGLES need a multiple of 3 indices, got {n}")
        return idx.reshape(-1, 3)
    if n < 3:
        raise fail(where, f"a triangle strip or fan needs at least 3 indices, got {n}")
    k = np.arange(n - 2)
    if mode == 5:  # strip: every other triangle swaps two corners to keep the winding
        even = (k % 2) == 0
        a = np.where(even, idx[k], idx[k + 1])
        b = np.where(even, idx[k + 1], idx[k])
        return np.stack([a, b, idx[k + 2]], axis=1)
    return np.stack([np.full(n - 2, idx[0]), idx[k + 1], idx[k + 2]], axis=1)


def _primitive(g: _Gltf, mi: int, pi: int) -> tuple[MeshData, dict[str, Any]] | None:
    w = f"meshes[{mi}].primitives[{pi}]"
    prim = _dict(g.doc["meshes"][mi]["primitives"][pi], w)
    warn = g.warnings.add
    mode = _int(prim.get("mode", 4), f"{w}.mode", 0, 6)
    if mode < 4:
        warn("points_and_lines", w, "point and line primitives carry no surface and are not imported")
        return None
    attrs = _dict(prim.get("attributes", {}), f"{w}.attributes")
    if "POSITION" not in attrs:
        warn("no_positions", w, "a primitive without POSITION has no geometry and is not imported")
        return None
    pos_i = _ref(attrs["POSITION"], g.accessors, f"{w}.attributes.POSITION", "accessors")
    pos = g.read(pos_i, f"{w}.attributes.POSITION", ("VEC3",), (5126,)).astype(np.float64)
    normals = None
    if "NORMAL" in attrs:
        ni = _ref(attrs["NORMAL"], g.accessors, f"{w}.attributes.NORMAL", "accessors")
        nrm = g.read(ni, f"{w}.attributes.NORMAL", ("VEC3",), (5126,)).astype(np.float64)
        if len(nrm) != len(pos):
            raise fail(f"accessors[{ni}].count", f"NORMAL has {len(nrm)} elements, POSITION has {len(pos)}")
        normals = nrm
    for attr in attrs:
        if attr.startswith("COLOR_"):
            warn("vertex_colors", f"{w}.attributes.{attr}", "vertex colours are ignored")
        elif attr.startswith(("JOINTS_", "WEIGHTS_")):
            warn("skins", f"{w}.attributes.{attr}", "skinning is ignored: meshes are imported in their bind pose")
    if "targets" in prim:
        warn("morph_targets", f"{w}.targets", "morph targets are ignored: the base geometry is imported")
    if "extensions" in prim:
        for name in _dict(prim["extensions"], f"{w}.extensions"):
            warn("primitive_extension", f"{w}.extensions.{name}",
                 "primitive extensions are ignored (the uncompressed data is read)")
    if "indices" in prim:
        ii = _ref(prim["indices"], g.accessors, f"{w}.indices", "accessors")
        idx = g.read(ii, f"{w}.indices", ("SCALAR",), _INDEX_TYPES)[:, 0].astype(np.int64)
        if len(idx) and int(idx.max()) >= len(pos):
            bad = int((idx >= len(pos)).sum())
            raise fail(f"accessors[{ii}]", f"{w}.indices: {bad} indices past the vertex count {len(pos)} "
                                           f"(largest {int(idx.max())})")
    else:
        idx = np.arange(len(pos), dtype=np.int64)
    faces = _triangles(mode, idx, f"{w}.indices")
    return MeshData(pos, faces, normals), prim


def import_gltf(data: bytes, binary_container: bool, files: Mapping[str, bytes], options: ImportOptions,
                source: str) -> tuple[dict[str, Any], dict[str, bytes], Warnings]:
    """(scene document, mesh blobs by path, warnings). Raises ImportProblem naming the part."""
    warnings = Warnings()
    if binary_container:
        raw_json, binary = _parse_glb(data)
        doc = _load_json(raw_json, "glb JSON chunk")
    else:
        binary = None
        doc = _load_json(data, "gltf")
    asset = _dict(doc.get("asset"), "asset")
    version = asset.get("version")
    if not (isinstance(version, str) and version.split(".")[0] == "2"):
        raise fail("asset.version", f"{version!r}: only glTF 2.x is supported"[:200])
    required = _list(doc, "extensionsRequired", "extensionsRequired")
    for list_name in ("extensionsRequired", "extensionsUsed"):
        for i, e in enumerate(_list(doc, list_name, list_name)):
            if not isinstance(e, str):
                raise fail(f"{list_name}[{i}]", f"must be an extension name (a string), got {type(e).__name__}")
    unsupported = [e for e in required if e not in SUPPORTED_EXTENSIONS]
    if unsupported:
        raise fail("extensionsRequired", f"the file requires {', '.join(map(str, unsupported))}, which this "
                                         f"importer does not read (it reads {', '.join(sorted(SUPPORTED_EXTENSIONS))})")
    for e in _list(doc, "extensionsUsed", "extensionsUsed"):
        if e not in SUPPORTED_EXTENSIONS:
            warnings.add("unknown_extension", f"extensionsUsed {e}", "extensions the importer does not read are "
                                                                     "ignored")
    for i, img in enumerate(_list(doc, "images", "images")):
        uri = _dict(img, f"images[{i}]").get("uri")
        if isinstance(uri, str) and not uri.startswith("data:"):
            problem = companion_uri_problem(uri)
            if problem is not None:
                raise fail(f"images[{i}].uri", problem)

    g = _Gltf(doc, binary, files, warnings)
    builder = SceneBuilder(source, warnings)
    nodes = _list(doc, "nodes", "nodes")
    meshes = _list(doc, "meshes", "meshes")
    materials = _list(doc, "materials", "materials")
    cameras = _list(doc, "cameras", "cameras")
    lights_ext = _dict(_dict(doc.get("extensions", {}), "extensions").get("KHR_lights_punctual", {}),
                       "extensions.KHR_lights_punctual")
    lights = _list(lights_ext, "lights", "extensions.KHR_lights_punctual.lights")
    for i, raw in enumerate(lights):  # validated even when unused, as the specification asks
        _light_params(raw, i)
    if _list(doc, "animations", "animations"):
        warnings.add("animations", "animations", "animations are ignored: the scene is imported at rest")
    if _list(doc, "skins", "skins"):
        warnings.add("skins", "skins", "skinning is ignored: meshes are imported in their bind pose")

    # the node graph must be a forest: one parent at most, no loops (checked for every node, used or not)
    children: set[int] = set()
    child_lists: list[list[int]] = []
    for i, raw in enumerate(nodes):
        kids: list[int] = []
        for k, c in enumerate(_list(_dict(raw, f"nodes[{i}]"), "children", f"nodes[{i}].children")):
            c = _ref(c, nodes, f"nodes[{i}].children[{k}]", "nodes")
            if c in children:
                raise fail(f"nodes[{i}].children[{k}]", f"nodes[{c}] has two parents: the node hierarchy must "
                                                         "be a forest")
            children.add(c)
            kids.append(c)
        child_lists.append(kids)
    reached = [i for i in range(len(nodes)) if i not in children]
    seen = set(reached)
    while reached:
        for c in child_lists[reached.pop()]:
            seen.add(c)
            reached.append(c)
    if len(seen) < len(nodes):
        looped = sorted(set(range(len(nodes))) - seen)
        raise fail(f"nodes[{looped[0]}].children", "nodes " + ", ".join(str(n) for n in looped[:10])
                   + " form a loop: the node hierarchy must be a forest")

    scenes = _list(doc, "scenes", "scenes")
    si = -1
    if scenes:
        si = _ref(doc.get("scene", 0), scenes, "scene", "scenes")
        roots_raw = _list(_dict(scenes[si], f"scenes[{si}]"), "nodes", f"scenes[{si}].nodes")
        roots = [_ref(r, nodes, f"scenes[{si}].nodes[{k}]", "nodes") for k, r in enumerate(roots_raw)]
        if len(scenes) > 1:
            warnings.add("scenes_beyond_default", "scenes", f"the file has {len(scenes)} scenes: only "
                                                            f"scenes[{si}] is imported")
    else:  # no scene: every node without a parent is a root
        roots = [i for i in range(len(nodes)) if i not in children]

    material_names: dict[int, str] = {}
    emissive: dict[str, tuple[float, float, float]] = {}
    prim_cache: dict[tuple[int, int], tuple[str, str] | None] = {}
    camera_doc: dict[str, Any] | None = None
    used_lights: set[int] = set()
    parent: dict[int, int] = {}
    stack: list[tuple[int, npt.NDArray[np.float64], int | None]] = [(r, np.eye(4), None) for r in reversed(roots)]
    for k, r in enumerate(roots):
        if r in parent:
            raise fail(f"scenes[{si}].nodes[{k}]", f"nodes[{r}] is listed twice as a root")
        parent[r] = -1
    while stack:
        ni, parent_world, _ = stack.pop()
        w = f"nodes[{ni}]"
        node = _dict(nodes[ni], w)
        world = parent_world @ _local_matrix(node, w)
        if not np.all(np.isfinite(world)):
            raise fail(w, "its world transform overflows (non-finite)")
        kids = _list(node, "children", f"{w}.children")
        for k in reversed(range(len(kids))):
            c = _ref(kids[k], nodes, f"{w}.children[{k}]", "nodes")
            if c in parent:
                raise fail(f"{w}.children[{k}]", f"nodes[{c}] is reached twice (a loop, or a node with two "
                                                 "parents): the node hierarchy must be a forest")
            parent[c] = ni
            stack.append((c, world, ni))
        if "skin" in node:
            warnings.add("skins", f"{w}.skin", "skinning is ignored: meshes are imported in their bind pose")
        if "weights" in node:
            warnings.add("morph_targets", f"{w}.weights", "morph targets are ignored: the base geometry is imported")
        singular = _singular(world)
        if "mesh" in node:
            mi = _ref(node["mesh"], meshes, f"{w}.mesh", "meshes")
            mesh = _dict(meshes[mi], f"meshes[{mi}]")
            prims = _list(mesh, "primitives", f"meshes[{mi}].primitives")
            if singular:
                warnings.add("zero_scale", w, "a node whose world transform is singular (a zero scale) shows "
                                              "nothing; its meshes are not imported")
            else:
                for pi in range(len(prims)):
                    key = (mi, pi)
                    if key not in prim_cache:
                        conv = _primitive(g, mi, pi)
                        if conv is None:
                            prim_cache[key] = None
                        else:
                            mesh_data, prim = conv
                            if "material" in prim:
                                mat_i = _ref(prim["material"], materials, f"meshes[{mi}].primitives[{pi}].material",
                                             "materials")
                            else:
                                mat_i = -1
                            if mat_i not in material_names:
                                material_names[mat_i] = (
                                    _material(g, mat_i, builder, emissive) if mat_i >= 0 else
                                    builder.add_material(pbr_material("default", (1, 1, 1), 1.0, 1.0,
                                                                      (0.04, 0.04, 0.04), (0, 0, 0)),
                                                         f"meshes[{mi}].primitives[{pi}]"))
                            stem = safe_name(mesh.get("name"), f"mesh{mi}") + f"_{pi}"
                            prim_cache[key] = (builder.add_mesh(mesh_data, stem, f"meshes[{mi}].primitives[{pi}]"),
                                               material_names[mat_i])
                    entry = prim_cache[key]
                    if entry is not None:
                        name = safe_name(node.get("name"), f"node{ni}") + (f"_{pi}" if len(prims) > 1 else "")
                        builder.add_object(entry[0], entry[1], world, name, w)
        if "camera" in node:
            ci = _ref(node["camera"], cameras, f"{w}.camera", "cameras")
            if camera_doc is None:
                camera_doc = _camera(_dict(cameras[ci], f"cameras[{ci}]"), ci, world, options, warnings)
            else:
                warnings.add("cameras_beyond_first", f"{w}.camera", "only the first camera of the scene "
                                                                    "(depth-first node order) is imported")
        ext = _dict(node.get("extensions", {}), f"{w}.extensions")
        for name in ext:
            if name != "KHR_lights_punctual":
                warnings.add("unknown_extension", f"{w}.extensions.{name}", "extensions the importer does not "
                                                                            "read are ignored")
        if "KHR_lights_punctual" in ext:
            lw = f"{w}.extensions.KHR_lights_punctual.light"
            li = _ref(_dict(ext["KHR_lights_punctual"], lw).get("light"), lights, lw,
                      "extensions.KHR_lights_punctual.lights")
            used_lights.add(li)
            _place_light(lights[li], li, world, builder, warnings, w)
    for li in range(len(lights)):
        if li not in used_lights:
            warnings.add("lights_not_placed", f"extensions.KHR_lights_punctual.lights[{li}]",
                         "a light no node of the scene places is not imported")
    if cameras and camera_doc is None:
        warnings.add("cameras_not_placed", "cameras", "no node of the scene places a camera: a default camera "
                                                      "frames the scene")
    builder.emissive_rect_lights(emissive)
    if camera_doc is None:
        if not cameras:
            warnings.add("no_camera", "cameras", "the file has no camera: a default camera looks along -z at the "
                                                 "scene's bounds")
        camera_doc = builder.default_camera(None, options)
    name = options.name or safe_name(asset.get("extras", {}).get("title") if isinstance(asset.get("extras"), dict)
                                     else None, safe_name(source.rsplit(".", 1)[0], "imported"))
    scene = {"name": name[:128], "camera": camera_doc, "materials": builder.materials,
             "objects": builder.objects, "lights": builder.lights}
    return scene, builder.meshes, warnings


def _light_params(raw: Any, i: int) -> dict[str, Any]:
    w = f"extensions.KHR_lights_punctual.lights[{i}]"
    light = _dict(raw, w)
    kind = light.get("type")
    if kind not in ("point", "spot", "directional"):
        raise fail(f"{w}.type", f"{kind!r} is not point, spot or directional"[:200])
    color = _nums(light.get("color", [1, 1, 1]), 3, f"{w}.color")
    if min(color) < 0:
        raise fail(f"{w}.color", "colour components must be >= 0")
    intensity = _num(light.get("intensity", 1.0), f"{w}.intensity")
    if intensity < 0:
        raise fail(f"{w}.intensity", f"must be >= 0, got {intensity}")
    if "range" in light:
        rng = _num(light["range"], f"{w}.range")
        if rng <= 0:
            raise fail(f"{w}.range", f"must be > 0, got {rng}")
    if kind == "spot":
        spot = _dict(light.get("spot"), f"{w}.spot")
        inner = _num(spot.get("innerConeAngle", 0.0), f"{w}.spot.innerConeAngle")
        outer = _num(spot.get("outerConeAngle", math.pi / 4), f"{w}.spot.outerConeAngle")
        if not (0 <= inner < outer <= math.pi / 2):
            raise fail(f"{w}.spot", f"cone angles must satisfy 0 <= innerConeAngle ({inner}) < outerConeAngle "
                                    f"({outer}) <= pi/2")
    return {"type": kind, "rgb": [c * intensity for c in color], "name": light.get("name"),
            "range": "range" in light}


def _place_light(raw: Any, li: int, world: npt.NDArray[np.float64], builder: SceneBuilder, warnings: Warnings,
                 where: str) -> None:
    p = _light_params(raw, li)
    lw = f"extensions.KHR_lights_punctual.lights[{li}]"
    if p["range"]:
        warnings.add("light_range", f"{lw}.range", "a light's range is ignored: light falls off as 1/d^2 "
                                                   "without a cut-off")
    name = safe_name(p["name"], f"light{li}")
    if p["type"] == "directional":
        d = world[:3, :3] @ np.array([0.0, 0.0, -1.0])
        if not np.linalg.norm(d) > 0:
            warnings.add("zero_scale", where, "a directional light under a singular transform has no direction; "
                                              "not imported")
            return
        builder.add_light({"type": "directional", "name": name, "direction": [float(x) for x in d],
                           "irradiance": p["rgb"]}, where)
        return
    if p["type"] == "spot":
        warnings.add("spot_as_point", lw, "spot lights become point lights of the same intensity: the project "
                                          "has no spot light, so the cone is dropped and light goes every way")
    builder.add_light({"type": "point", "name": name, "position": [float(x) for x in world[:3, 3]],
                       "intensity": p["rgb"]}, where)


def _camera(cam: dict[str, Any], ci: int, world: npt.NDArray[np.float64], options: ImportOptions,
            warnings: Warnings) -> dict[str, Any]:
    w = f"cameras[{ci}]"
    eye = world[:3, 3]
    fwd = world[:3, :3] @ np.array([0.0, 0.0, -1.0])
    up = world[:3, :3] @ np.array([0.0, 1.0, 0.0])
    nf, nu = float(np.linalg.norm(fwd)), float(np.linalg.norm(up))
    if not (nf > 0 and nu > 0):
        raise fail(w, "the camera's node has a singular transform: no view direction")
    fwd, up = fwd / nf, up / nu
    look = eye + fwd * max(1.0, float(np.abs(eye).max()) * 1e-3)
    kind = cam.get("type")
    params = cam.get(kind) if isinstance(kind, str) else None
    if isinstance(params, dict) and ("znear" in params or "zfar" in params):
        warnings.add("clip_planes", f"{w}.{kind}", "camera clipping planes (znear, zfar) are ignored")
    if kind == "perspective":
        p = _dict(cam.get("perspective"), f"{w}.perspective")
        yfov = _num(p.get("yfov"), f"{w}.perspective.yfov")
        if not 0 < yfov < math.pi:
            raise fail(f"{w}.perspective.yfov", f"{yfov} is not in (0, pi)")
        aspect = _num(p["aspectRatio"], f"{w}.perspective.aspectRatio") if "aspectRatio" in p else None
        if aspect is not None and aspect <= 0:
            raise fail(f"{w}.perspective.aspectRatio", f"must be > 0, got {aspect}")
        width, height = resolution(aspect or 4 / 3, options)
        return {"type": "perspective", "eye": [float(x) for x in eye], "look_at": [float(x) for x in look],
                "up": [float(x) for x in up], "fov_y_deg": math.degrees(yfov), "width": width, "height": height}
    if kind == "orthographic":
        o = _dict(cam.get("orthographic"), f"{w}.orthographic")
        xmag = _num(o.get("xmag"), f"{w}.orthographic.xmag")
        ymag = _num(o.get("ymag"), f"{w}.orthographic.ymag")
        if xmag == 0 or ymag == 0:
            raise fail(f"{w}.orthographic", "xmag and ymag must be nonzero")
        width, height = resolution(abs(xmag / ymag), options)
        return {"type": "orthographic", "eye": [float(x) for x in eye], "look_at": [float(x) for x in look],
                "up": [float(x) for x in up], "ortho_height": 2 * abs(ymag), "width": width, "height": height}
    raise fail(f"{w}.type", f"{kind!r} is not perspective or orthographic"[:200])
