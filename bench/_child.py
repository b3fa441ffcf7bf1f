"""Entry point of the benchmarks' child processes, in any side's interpreter:

    python bench/_child.py MODULE ARGS...   ->   bench.MODULE.child_main(ARGS)

Run as a file (not ``-m``) with this folder's parent kept off ``sys.path``, so that ``import tmrl``
in the original's interpreter finds the installed tmrl 0.7.1 and not this checkout; the ``bench``
package itself is loaded from this folder by path.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path


def main() -> None:
    here = Path(__file__).resolve().parent
    # sys.path[0] is this folder: drop it, so that its modules load only as bench.<name>.
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != here]
    spec = importlib.util.spec_from_file_location("bench", here / "__init__.py",
                                                  submodule_search_locations=[str(here)])
    assert spec is not None and spec.loader is not None
    package = importlib.util.module_from_spec(spec)
    sys.modules["bench"] = package
    spec.loader.exec_module(package)
    module = importlib.import_module(f"bench.{sys.argv[1]}")
    try:
        module.child_main(sys.argv[2:])
    except KeyboardInterrupt:  # the harness stops role processes with SIGINT
        pass


if __name__ == "__main__":
    main()
