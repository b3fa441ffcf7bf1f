"""``python -m bench --list`` and ``python -m bench NAME [options]``."""

from __future__ import annotations

import importlib
import sys

from bench import BENCHMARKS


def _describe(name: str) -> str:
    doc = importlib.import_module(f"bench.{name}").__doc__ or ""
    return doc.strip().split("\n\n")[0].replace("\n", " ")


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help", "--list"):
        print("usage: python -m bench NAME [options]   (python -m bench NAME --help for its options)\n")
        for name in BENCHMARKS:
            print(f"  {name:20s} {_describe(name)}")
        print("\nEach run also writes bench/out/NAME-<timestamp>.jsonl. The other sides install with "
              "bench/anchors/install_tmrl.sh and bench/anchors/install_sb3.sh.")
        return
    name, rest = argv[0], argv[1:]
    if name not in BENCHMARKS:
        sys.exit(f"python -m bench: unknown benchmark {name!r}; python -m bench --list shows them")
    sys.argv = [f"python -m bench {name}", *rest]
    importlib.import_module(f"bench.{name}").main(rest)


if __name__ == "__main__":
    main()
