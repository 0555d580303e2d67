"""The render-method registry (engine/methods.py): parsing, ranges, the round trip of every wire name,
bad input, and that the request schema and the reference renderer's settings read it."""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.methods import (
    IBRT_GENERATIONS,
    LDC,
    LDC_IBRT,
    LDC_LLF,
    METHODS,
    REFERENCE,
    Param,
    allowed_forms,
    get_method,
    method_needs_bake,
    method_pattern,
    parse_method,
    wire_names,
)


def test_every_wire_name_round_trips_and_matches_the_pattern() -> None:
    names = wire_names()
    assert names[:3] == ["reference", "ldc", "ldc+llf"]
    assert names[3:] == [f"ldc+ibrt:{k}" for k in range(0, 9)]
    assert len(set(names)) == len(names)
    for name in names:
        spec = parse_method(name)
        assert spec.wire == name
        assert re.fullmatch(method_pattern(), name)
    assert method_pattern() == r"^(reference|ldc|ldc\+llf|ldc\+ibrt:[0-8])$"


def test_what_each_method_needs() -> None:
    ref, ldc, llf = parse_method("reference"), parse_method("ldc"), parse_method("ldc+llf")
    assert (ref.needs_bake, ref.bake, ref.gathers, ref.ibrt_generations) == (False, (), False, 0)
    assert (ldc.needs_bake, ldc.bake, ldc.gathers, ldc.ibrt_generations) == (True, ("LDC",), False, 0)
    assert (llf.needs_bake, llf.bake, llf.gathers, llf.ibrt_generations) == (True, ("LDC", "LLF"), True, 0)
    for k in range(9):
        spec = parse_method(f"ldc+ibrt:{k}")
        assert spec.method is LDC_IBRT and spec.name == "ldc+ibrt" and spec.arg == k
        assert (spec.needs_bake, spec.bake, spec.gathers, spec.ibrt_generations) == (True, ("LDC", "LLF"), True, k)
    assert [method_needs_bake(n) for n in ("reference", "ldc", "ldc+llf", "ldc+ibrt:8")] == [False, True, True, True]
    assert [m.form for m in METHODS] == ["reference", "ldc", "ldc+llf", "ldc+ibrt:k"]
    assert get_method("ldc+llf") is LDC_LLF and get_method("ldc") is LDC
    for m in METHODS:  # a capability list can show every entry
        assert m.summary and m.cost


@pytest.mark.parametrize("bad", [
    "", "LDC", " ldc", "ldc ", "ref", "reference:1", "ldc:0", "ldc+llf:1", "ldc+ibrt", "ldc+ibrt:", "ldc+ibrt:9",
    "ldc+ibrt:-1", "ldc+ibrt:03", "ldc+ibrt:+3", "ldc+ibrt: 3", "ldc+ibrt:3 ", "ldc+ibrt:3\n", "ldc+ibrt:x",
    "ldc+ibrt:1.0", "ldc+ibrt:1_0", "ldc+ibrt:\u0663", "ldc+ibrt:1:2", "x" * 200, "ldc+ibrt:" + "9" * 5000,
])
def test_bad_method_strings_name_the_allowed_forms(bad: str) -> None:
    with pytest.raises(InvalidInputError) as err:
        parse_method(bad)
    assert isinstance(err.value, ValueError)
    msg = str(err.value)
    assert "0..8" in msg and "ldc+ibrt" in msg
    assert len(msg) < 200  # a long input is cut, not echoed whole


@pytest.mark.parametrize("bad", [None, 3, b"ldc", ["ldc"]])
def test_non_strings_are_refused(bad: object) -> None:
    with pytest.raises(InvalidInputError, match="string"):
        parse_method(bad)
    with pytest.raises(InvalidInputError):
        get_method("ldc+ibrt:1")  # a wire string is not an entry name


def test_allowed_forms_text() -> None:
    assert allowed_forms() == "'reference', 'ldc', 'ldc+llf' or 'ldc+ibrt:k' with k in 0..8"
    assert allowed_forms(needs_bake=True) == "'ldc', 'ldc+llf' or 'ldc+ibrt:k' with k in 0..8"
    assert allowed_forms(needs_bake=False) == "'reference'"


def test_param_ranges() -> None:
    k = IBRT_GENERATIONS
    assert (k.low, k.high, k.default) == (0, 8, 1)
    assert k.check(0) == 0 and k.check(np.int64(8)) == 8 and type(k.check(np.int32(3))) is int
    for bad in (-1, 9, True, 1.0, "1", None, np.float64(2.0)):
        with pytest.raises(InvalidInputError, match=r"\[0, 8\]"):
            k.check(bad)
    with pytest.raises(InvalidInputError, match="ibrt_generations"):
        k.check(9, "ibrt_generations")
    assert LDC_IBRT.spec().arg == 1 and LDC_IBRT.spec(5).wire == "ldc+ibrt:5"
    with pytest.raises(InvalidInputError):
        LDC_IBRT.spec(9)
    with pytest.raises(InvalidInputError, match="no parameter"):
        LDC.spec(2)
    with pytest.raises(ValueError, match="outside"):
        Param("x", 5, 0, 4, "a default out of its own range")
    spp = REFERENCE.param("spp")
    assert (spp.low, spp.high, spp.default) == (1, 4096, 4)
    with pytest.raises(KeyError):
        REFERENCE.param("nope")
    for m in METHODS:
        for p in m.params:
            assert p.doc and (p.optional or p.contains(p.default))


def test_reference_params_model_reads_the_registry() -> None:
    """``ReferenceRenderParams`` has exactly the registry's parameters, with its ranges and defaults."""
    from pydantic import ValidationError

    from api_schemas.service import ReferenceRenderParams

    fields = ReferenceRenderParams.model_fields
    assert list(fields) == [p.name for p in REFERENCE.params]
    defaults = ReferenceRenderParams()
    for p in REFERENCE.params:
        assert getattr(defaults, p.name) == p.default
        # the bounds themselves when included, just inside them when excluded (float parameters)
        step = 0 if p.kind == "int" else 1e-9 * max(1.0, abs(p.high))
        ReferenceRenderParams.model_validate({p.name: p.low + step if p.low_open else p.low})
        ReferenceRenderParams.model_validate({p.name: p.high - step if p.high_open else p.high})
        outside = [p.low - 1, p.high + 1] + ([p.low] if p.low_open else []) + ([p.high] if p.high_open else [])
        for out in outside:
            with pytest.raises(ValidationError):
                ReferenceRenderParams.model_validate({p.name: out})


def test_request_schema_validates_through_the_registry() -> None:
    from pydantic import ValidationError

    from api_schemas.service import METHOD_PATTERN, RenderRequest

    assert METHOD_PATTERN == method_pattern()
    for name in wire_names():
        assert RenderRequest.model_validate({"scene_id": "0" * 64, "method": name}).method == name
    with pytest.raises(ValidationError) as err:
        RenderRequest.model_validate({"scene_id": "0" * 64, "method": "ldc+ibrt:03"})
    e = err.value.errors()[0]
    assert e["type"] == "render_method"
    assert e["msg"] == ("method must be 'reference', 'ldc', 'ldc+llf' or 'ldc+ibrt:k' with k in 0..8, "
                        "got 'ldc+ibrt:03'")
    schema = RenderRequest.model_json_schema()["properties"]["method"]
    assert schema["pattern"] == method_pattern()
    assert schema["description"] == "reference | ldc | ldc+llf | ldc+ibrt:k (k = 0..8 reflection generations)"


def test_registry_is_pure_python() -> None:
    code = "import sys, engine.methods; print(sorted(m for m in sys.modules if m.startswith(('numba', 'numpy'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr
