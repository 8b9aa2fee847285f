"""The on-disk kernel cache across processes (``rayaccel._jit``)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

FACTORY = textwrap.dedent(
    """
    import functools
    import sys

    from rayaccel._jit import cpu_kernel


    @functools.cache
    def add_constant(value):
        @cpu_kernel()
        def body(x, n):
            # Large enough that LLVM keeps it a call rather than inlining it.
            total = 0.0
            for i in range(n):
                total += (x * i + value) % 7.0 - (x - i) % 5.0 + (i * value) % 3.0
                total -= (x * i + value) % 7.0 - (x - i) % 5.0 + (i * value) % 3.0
                total += (x * i) % 11.0 - (x + i) % 13.0 + (i * x) % 17.0
                total -= (x * i) % 11.0 - (x + i) % 13.0 + (i * x) % 17.0
            return x + value + total

        @cpu_kernel()
        def kernel(x):
            return 0.5 * (body(x, 3) + body(x, 5))

        return kernel


    if __name__ == "__main__":
        print(*(add_constant(int(v))(1.0) for v in sys.argv[1:]))
    """
)


def test_closures_compiled_in_different_processes_keep_their_own_code(tmp_path):
    # Two processes compile one factory's closures in the same order, so numba's
    # per-process counters give them the same symbol names but for the qualified name;
    # a third process loads both from the cache and must run each one's own code.
    script = tmp_path / "factory.py"
    script.write_text(FACTORY)
    # One hash seed: numba's symbol names spell the fastmath flags in set order.
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "PYTHONHASHSEED": "0"}

    def run(*values: str) -> str:
        done = subprocess.run(
            [sys.executable, str(script), *values],
            env=env, capture_output=True, text=True, timeout=300, check=False,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        return done.stdout.strip()

    assert run("1") == "2.0"
    assert run("2") == "3.0"
    assert run("1", "2") == "2.0 3.0"
    assert run("2", "1") == "3.0 2.0"
