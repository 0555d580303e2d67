"""engine.memory: the workers' malloc policy keeps freed image-sized buffers for the next render."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# Run in a fresh interpreter each: the policy is process-wide and set once.
_PROBE = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from engine.memory import keep_freed_memory, malloc_policy
    if sys.argv[1] == "on":
        assert keep_freed_memory(64 << 20)
    else:
        assert not malloc_policy()["active"]
    def faults(n):
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        a = np.ones(n // 8)  # touch every page
        f = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0
        del a
        return f
    faults(6 << 20)      # a render's buffers ...
    faults(3 << 20)
    print(faults(24 << 20), faults(24 << 20))  # ... then another kind's, twice
""")


def _second_faults(mode: str) -> tuple[int, int]:
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, check=True)
    a, b = out.stdout.split()
    return int(a), int(b)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc")
def test_freed_buffers_are_reused_without_page_faults():
    # (numpy asks for transparent huge pages on big arrays, so a fresh 24 MiB buffer costs a few
    # hundred faults here rather than 6,144; measured: on 0, off 266-777)
    _, second_on = _second_faults("on")
    assert second_on <= 16, f"with the policy a freed 24 MiB buffer came back with {second_on} page faults"
    # glibc's default maps the same buffer anew: this is what the policy is for
    _, second_off = _second_faults("off")
    assert second_off >= 64, f"without the policy: {second_off} page faults (expected a fresh mapping)"


def test_policy_is_set_once_and_reported():
    code = textwrap.dedent("""
        from engine.memory import keep_freed_memory, malloc_policy
        assert keep_freed_memory(0) is False          # 0: glibc's defaults, and that holds
        assert keep_freed_memory(64 << 20) is False
        assert malloc_policy() == {"active": False, "keep_bytes": 0, "mmap_threshold_bytes": None}
    """)
    subprocess.run([sys.executable, "-c", code], check=True)
