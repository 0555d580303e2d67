"""Wavefront OBJ with MTL materials -> the project's scene document and mesh blobs.

One mesh blob per material used (``usemtl``); polygons are split into triangle fans; relative
(negative) indices resolve against the vertices read so far. Errors name the file and line
(``CornellBox.obj:12``). The ``.mtl`` files ``mtllib`` names come from the same upload.
"""

from __future__ import annotations

import urllib.parse
from collections.abc import Mapping
from typing import Any

import numpy as np

from api_schemas.scene import MAX_MESH_FACES, MAX_MESH_VERTICES
from producer.scene_import.common import (
    ImportOptions,
    MeshData,
    SceneBuilder,
    Warnings,
    companion_uri_problem,
    fail,
    phong_material,
    safe_name,
)

__all__ = ["import_obj", "obj_companions"]

_IGNORED = {b"vt", b"vp", b"o", b"g", b"s", b"mg"}
_UNSUPPORTED = {b"l": "lines", b"p": "points", b"curv": "free-form geometry", b"curv2": "free-form geometry",
                b"surf": "free-form geometry", b"cstype": "free-form geometry", b"deg": "free-form geometry",
                b"bmat": "free-form geometry", b"step": "free-form geometry", b"parm": "free-form geometry",
                b"trim": "free-form geometry", b"hole": "free-form geometry", b"scrv": "free-form geometry",
                b"sp": "free-form geometry", b"end": "free-form geometry", b"con": "free-form geometry"}


def _text(data: bytes, source: str) -> list[bytes]:
    if b"\x00" in data:
        raise fail(source, "not an OBJ/MTL text file: it contains NUL bytes")
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    lines = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n").split(b"\n")
    out: list[bytes] = []
    carry = b""
    for ln in lines:  # a trailing backslash continues the line
        ln = carry + ln
        if ln.endswith(b"\\"):
            carry = ln[:-1] + b" "
            out.append(b"")
            continue
        carry = b""
        out.append(ln.split(b"#", 1)[0].strip())
    return out


def _floats(words: list[bytes], n: int, where: str) -> list[float]:
    if len(words) < n:
        raise fail(where, f"needs {n} numbers, got {len(words)}")
    try:
        vals = [float(w) for w in words[:n]]
    except ValueError:
        raise fail(where, f"not a number in {b' '.join(words[:n]).decode('latin-1')[:80]!r}") from None
    if not all(np.isfinite(vals)):
        raise fail(where, "NaN or infinite value")
    return vals


def obj_companions(data: bytes) -> list[str]:
    """The ``mtllib`` files an OBJ names (for a client to send them along)."""
    out: list[str] = []
    for ln in _text(data, "obj") if b"\x00" not in data else []:
        if ln.startswith(b"mtllib"):
            for word in ln.split()[1:]:
                name = urllib.parse.unquote(word.decode("utf-8", "replace"))
                if companion_uri_problem(name) is None and name not in out:
                    out.append(name)
    return out


def _parse_mtl(data: bytes, source: str, warnings: Warnings) -> dict[str, dict[str, Any]]:
    mats: dict[str, dict[str, Any]] = {}
    cur: dict[str, Any] | None = None
    for n, ln in enumerate(_text(data, source), start=1):
        if not ln:
            continue
        words = ln.split()
        key, args = words[0], words[1:]
        where = f"{source}:{n}"
        if key == b"newmtl":
            name = b" ".join(args).decode("utf-8", "replace")
            cur = {"name": name, "Kd": [0.8, 0.8, 0.8], "Ks": [0.0, 0.0, 0.0], "Ke": [0.0, 0.0, 0.0],
                   "Ns": 0.0, "illum": 2, "where": where}
            mats[name] = cur
            continue
        if cur is None:
            raise fail(where, f"{key.decode('latin-1')[:20]!r} before any newmtl")
        if key in (b"Kd", b"Ks", b"Ke"):
            if args and args[0] in (b"spectral", b"xyz"):
                warnings.add("mtl_spectral", where, "spectral and XYZ colours are not read; the default is kept")
                continue
            vals = _floats(args, 1, where)
            vals = _floats(args, 3, where) if len(args) >= 3 else vals * 3
            if min(vals) < 0:
                raise fail(where, "colour components must be >= 0")
            cur[key.decode()] = vals
        elif key == b"Ns":
            cur["Ns"] = max(0.0, _floats(args, 1, where)[0])
        elif key == b"illum":
            try:
                cur["illum"] = int(args[0])
            except (ValueError, IndexError):
                raise fail(where, "illum needs an integer") from None
        elif key in (b"d", b"Tr"):
            numbers = [v for v in args if not v.startswith(b"-")]
            x = _floats(numbers, 1, where)[0] if numbers else 1.0
            if (key == b"d" and x < 1) or (key == b"Tr" and x > 0):
                warnings.add("transparency", where, "transparency (d, Tr) is ignored: surfaces are opaque")
        elif key.startswith(b"map_") or key in (b"bump", b"disp", b"decal", b"refl", b"norm"):
            warnings.add("textures", where, "texture maps are ignored: each material uses its constant colours")
        elif key in (b"Ka", b"Ni", b"Tf", b"sharpness"):
            pass  # ambient colour (the scene's ambient is 0), refraction index and filter: see docs
        else:
            warnings.add("mtl_statement", where, "MTL statements the importer does not read are ignored "
                                                 "(PBR extensions Pr, Pm, ...)")
    return mats


def _material_doc(m: dict[str, Any], name: str, warnings: Warnings) -> dict[str, Any]:
    illum = int(m["illum"])
    kd, ks, ke = tuple(m["Kd"]), tuple(m["Ks"]), tuple(m["Ke"])
    zero = (0.0, 0.0, 0.0)
    where = m["where"]
    if illum in (0, 1):
        return phong_material(name, kd, zero, 0.0, zero, ke, where, warnings)
    if illum == 2:
        return phong_material(name, kd, ks, m["Ns"], zero, ke, where, warnings)
    if illum in (4, 6, 7, 9):
        warnings.add("refraction", where, "glass and refraction (illum 4, 6, 7, 9) are not rendered: the surface "
                                          "keeps its mirror reflection Ks and its diffuse colour")
    elif illum not in (3, 5, 8):
        warnings.add("illum_model", where, f"illumination model {illum} is read as model 2 (Phong highlight)")
        return phong_material(name, kd, ks, m["Ns"], zero, ke, where, warnings)
    # illum 3, 5, 8 (and the glass models above): Ks is a mirror reflection
    if illum == 5:
        warnings.add("fresnel", where, "Fresnel mirrors (illum 5) reflect Ks at every angle")
    return phong_material(name, kd, zero, 0.0, ks, ke, where, warnings)


def import_obj(data: bytes, files: Mapping[str, bytes], options: ImportOptions,
               source: str) -> tuple[dict[str, Any], dict[str, bytes], Warnings]:
    warnings = Warnings()
    lines = _text(data, source)
    positions: list[list[float]] = []
    normals: list[list[float]] = []
    # per material name: lists of (position index, normal index or -1) triangles
    groups: dict[str, list[tuple[int, int]]] = {}
    group_first_line: dict[str, str] = {}
    mtl: dict[str, dict[str, Any]] = {}
    current = ""
    n_faces = 0
    for n, ln in enumerate(lines, start=1):
        if not ln:
            continue
        words = ln.split()
        key = words[0]
        where = f"{source}:{n}"
        if key == b"v":
            if len(words) > 5:
                warnings.add("vertex_colors", where, "vertex colours are ignored")
            positions.append(_floats(words[1:], 3, where))
            if len(positions) > MAX_MESH_VERTICES:
                raise fail(where, f"more than {MAX_MESH_VERTICES} vertices (the scene limit)")
        elif key == b"vn":
            normals.append(_floats(words[1:], 3, where))
            if len(normals) > MAX_MESH_VERTICES:
                raise fail(where, f"more than {MAX_MESH_VERTICES} normals (the scene limit)")
        elif key == b"f":
            corners = words[1:]
            if len(corners) < 3:
                raise fail(where, f"a face needs at least 3 corners, got {len(corners)}")
            refs: list[tuple[int, int]] = []
            for c in corners:
                parts = c.split(b"/")
                try:
                    vi = int(parts[0])
                    ni = int(parts[2]) if len(parts) > 2 and parts[2] else 0
                except ValueError:
                    raise fail(where, f"face corner {c.decode('latin-1')[:40]!r} is not v, v/vt, v//vn or "
                                      "v/vt/vn with integer indices") from None
                refs.append((_resolve(vi, len(positions), where, "vertex", "vertices"),
                             _resolve(ni, len(normals), where, "normal", "normals") if ni else -1))
            tris = groups.setdefault(current, [])
            group_first_line.setdefault(current, where)
            for k in range(1, len(refs) - 1):
                tris += [refs[0], refs[k], refs[k + 1]]
            n_faces += len(refs) - 2
            if n_faces > MAX_MESH_FACES:
                raise fail(where, f"more than {MAX_MESH_FACES} triangles (the scene limit)")
        elif key == b"usemtl":
            current = b" ".join(words[1:]).decode("utf-8", "replace")
        elif key == b"mtllib":
            for word in words[1:]:
                name = urllib.parse.unquote(word.decode("utf-8", "replace"))
                problem = companion_uri_problem(name)
                if problem is not None:
                    raise fail(where, f"mtllib {problem}")
                if name not in files:
                    raise fail(where, f"the material file {name!r} is missing: upload it as a file part of "
                                      "that name")
                for mname, m in _parse_mtl(files[name], name, warnings).items():
                    mtl.setdefault(mname, m)
        elif key in _IGNORED:
            continue
        elif key in _UNSUPPORTED:
            warnings.add(_UNSUPPORTED[key].replace(" ", "_").replace("-", "_"), where,
                         f"{_UNSUPPORTED[key]} carry no surface the project renders and are not imported")
        else:
            warnings.add("obj_statement", where, "OBJ statements the importer does not read are ignored")
    if not groups:
        raise fail(source, "the file has no faces")

    builder = SceneBuilder(source, warnings)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    emissive: dict[str, tuple[float, float, float]] = {}
    for mname, tri_corners in groups.items():
        if mname in mtl:
            doc = _material_doc(mtl[mname], safe_name(mname, "material"), warnings)
        else:
            warnings.add("unknown_material", group_first_line[mname],
                         "faces without a material, or naming one no MTL file defines, get a grey diffuse "
                         "material (kd 0.8)")
            doc = {"name": safe_name(mname, "default"), "kd": [0.8, 0.8, 0.8]}
        stored = builder.add_material(doc, group_first_line[mname])
        if max(doc.get("emission", [0.0])) > 0:
            e = doc["emission"]
            emissive[stored] = (e[0], e[1], e[2])
        ref = np.asarray(tri_corners, dtype=np.int64).reshape(-1, 2)
        if np.all(ref[:, 1] >= 0):
            keys, inverse = np.unique(ref, axis=0, return_inverse=True)
            mesh = MeshData(pos[keys[:, 0]], inverse.reshape(-1, 3).astype(np.int64), nrm[keys[:, 1]])
        else:
            if np.any(ref[:, 1] >= 0):
                warnings.add("partial_normals", group_first_line[mname], "a material's faces give normals for "
                                                                         "some corners only: all are recomputed")
            used, inverse = np.unique(ref[:, 0], return_inverse=True)
            mesh = MeshData(pos[used], inverse.reshape(-1, 3).astype(np.int64), None)
        path = builder.add_mesh(mesh, stored, group_first_line[mname])
        builder.add_object(path, stored, None, stored, group_first_line[mname])
    builder.emissive_rect_lights(emissive)
    warnings.add("no_camera", source, "OBJ has no camera: a default camera looks along -z at the scene's bounds")
    camera = builder.default_camera(None, options)
    name = options.name or safe_name(source.rsplit(".", 1)[0], "imported")
    scene = {"name": name[:128], "camera": camera, "materials": builder.materials, "objects": builder.objects,
             "lights": builder.lights}
    return scene, builder.meshes, warnings


def _resolve(i: int, n: int, where: str, what: str, plural: str) -> int:
    """A 1-based or negative (relative) OBJ index -> 0-based, checked against the n read so far."""
    if i > 0 and i <= n:
        return i - 1
    if i < 0 and -i <= n:
        return n + i
    raise fail(where, f"{what} index {i} is out of range: {n} {plural} defined so far "
                      f"(OBJ indices start at 1; negative ones count back)")
