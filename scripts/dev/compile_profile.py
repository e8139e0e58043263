"""What the test suite compiles, from the lines tests/compile_log.py writes
(`TTMJX_COMPILE_LOG=/tmp/compiles.jsonl python -m pytest ...`), or from a JAX compilation cache
directory (each entry keeps the seconds its compile took, whole seconds).

    python scripts/dev/compile_profile.py /tmp/compiles.jsonl [--top 25]
    python scripts/dev/compile_profile.py .jax_cache

Prints the seconds XLA spent compiling, by program name (how many distinct programs of that
name: a name compiled for many input shapes is a candidate for sharing one shape), by test, and
the seconds spent reading programs back from the persistent cache."""
import argparse
import collections
import json
import os
import zlib


def cache_rows(directory: str) -> list[dict]:
    """One row per entry of a JAX persistent compilation cache: program name, compile seconds."""
    try:
        import zstandard
    except ImportError:
        zstandard = None
    rows = []
    for name in sorted(os.listdir(directory)):
        if not name.endswith("-cache"):
            continue
        with open(os.path.join(directory, name), "rb") as f:
            blob = f.read()
        try:
            raw = zlib.decompress(blob)
        except zlib.error:
            if zstandard is None:
                raise SystemExit(f"{name}: not zlib; install zstandard to read this cache") from None
            raw = zstandard.ZstdDecompressor().decompress(blob, max_output_size=1 << 34)
        # jax/_src/compilation_cache.py: 4 bytes of int(compile seconds), big-endian, then the
        # executable; int() truncates, so half a second is added back on average.
        seconds = int.from_bytes(raw[:4], "big") + 0.5
        rows.append({"program": name.rsplit("-", 2)[0], "seconds": seconds, "compiled": True,
                     "test": "?", "types": name.rsplit("-", 2)[1]})
    return rows


def log_rows(path: str) -> list[dict]:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def table(title: str, counts: dict, seconds: dict, top: int, what: str) -> None:
    print(f"\n{title}")
    print(f"{'seconds':>9} {what:>9}  name")
    for key, s in sorted(seconds.items(), key=lambda kv: -kv[1])[:top]:
        print(f"{s:9.1f} {counts[key]:9d}  {key}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source", help="a TTMJX_COMPILE_LOG file or a JAX compilation cache directory")
    ap.add_argument("--top", type=int, default=25, help="rows per table (default 25)")
    a = ap.parse_args()
    rows = cache_rows(a.source) if os.path.isdir(a.source) else log_rows(a.source)
    compiled = [r for r in rows if r["compiled"]]
    read = [r for r in rows if not r["compiled"]]
    print(f"{len(compiled)} programs compiled in {sum(r['seconds'] for r in compiled):.0f} s; "
          f"{len(read)} read from the cache in {sum(r['seconds'] for r in read):.0f} s")
    by_name_s, by_name_n = collections.Counter(), collections.defaultdict(set)
    by_test_s, by_test_n = collections.Counter(), collections.Counter()
    for r in compiled:
        by_name_s[r["program"]] += r["seconds"]
        by_name_n[r["program"]].add(r["types"])
        by_test_s[r["test"]] += r["seconds"]
        by_test_n[r["test"]] += 1
    table("compile seconds by program name (programs: distinct input and output types)", {k: len(v) for k, v in by_name_n.items()},
          by_name_s, a.top, "programs")
    if any(r["test"] != "?" for r in compiled):
        table("compile seconds by test (the first test to need a program compiles it)", by_test_n, by_test_s,
              a.top, "programs")


if __name__ == "__main__":
    main()
