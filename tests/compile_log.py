"""Opt-in profile of what the suite compiles: with TTMJX_COMPILE_LOG=FILE, every program a test
process hands to XLA appends one JSON line to FILE: the test running, the program's name, its
input and output types (a hash and their first 300 characters), the seconds spent (compile, or
read from the persistent cache) and whether XLA compiled it. Subprocesses (`ttmjx ...`) are not seen. scripts/dev/compile_profile.py sums the lines.

Loaded by tests/conftest.py only when the variable is set; the suite is otherwise untouched."""
import hashlib
import json
import os
import time

from jax._src import compiler

_current = {"test": "(collection)"}


def _input_types(computation) -> str:
    """The main function's input and output types, as MLIR prints them (shapes and dtypes)."""
    for op in computation.body.operations:
        if str(op.attributes["sym_name"]).strip('"') == "main":
            return str(op.attributes["function_type"])   # (inputs) -> (outputs)
    return "?"


def install(path: str) -> None:
    """Wrap JAX's compile entry points so that each program is logged to `path`."""
    real_cached, real_backend = compiler.compile_or_get_cached, compiler.backend_compile_and_load
    compiled = []

    def backend_compile_and_load(*args, **kwargs):
        compiled.append(True)
        return real_backend(*args, **kwargs)

    def compile_or_get_cached(backend, computation, *args, **kwargs):
        compiled.clear()
        t0 = time.perf_counter()
        out = real_cached(backend, computation, *args, **kwargs)
        seconds = time.perf_counter() - t0
        name = str(computation.operation.attributes["sym_name"]).strip('"')
        types = _input_types(computation)
        line = {"test": _current["test"], "program": name, "seconds": round(seconds, 3),
                "compiled": bool(compiled), "types": hashlib.sha1(types.encode()).hexdigest()[:12],
                "signature": types[:300], "pid": os.getpid()}
        with open(path, "a") as f:
            f.write(json.dumps(line) + "\n")
        return out

    compiler.backend_compile_and_load = backend_compile_and_load
    compiler.compile_or_get_cached = compile_or_get_cached


def set_test(nodeid: str) -> None:
    _current["test"] = nodeid
