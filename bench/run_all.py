"""Run every benchmark in bench/ and print its figures."""

import runpy
import sys
from pathlib import Path

here = Path(__file__).resolve().parent
for script in sorted(here.glob("bench_*.py")):
    print(f"== {script.name}", flush=True)
    sys.argv = [str(script)]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as err:  # a bench that ends with its exit status: go on to the next
        if err.code not in (None, 0):
            print(f"== {script.name} exited {err.code}", flush=True)
