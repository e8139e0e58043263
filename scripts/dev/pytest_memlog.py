"""A pytest plugin that logs, after each test module, the process's resident memory and its
number of memory mappings (/proc/self/maps, Linux). The whole suite runs in one process, and
each XLA:CPU executable holds mappings: past vm.max_map_count (65,530 by default) the next
compile fails with LLVM's "Cannot allocate memory" (tests/conftest.py releases them per module).

    PYTHONPATH=scripts python -m pytest -p pytest_memlog     # -> memlog.txt (or $MEMLOG)
"""
import os
import time

_T0 = time.time()


def _rss_mb_and_maps() -> tuple[int, int]:
    rss = 0
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                rss = int(line.split()[1]) // 1024
    with open("/proc/self/maps") as f:
        maps = sum(1 for _ in f)
    return rss, maps


def pytest_runtest_teardown(item, nextitem):
    module = item.module.__name__
    if nextitem is None or nextitem.module.__name__ != module:
        rss, maps = _rss_mb_and_maps()
        with open(os.environ.get("MEMLOG", "memlog.txt"), "a") as f:
            f.write(f"{time.time() - _T0:7.0f} s  {module:32s} rss {rss} MB  maps {maps}\n")
