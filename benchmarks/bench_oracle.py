"""Oracle build time (oracle_graph.py): median time to build the 5-block oracle graph from
scratch (grid search over permutation classes + lift to all permutations), every cached table
(permutations, byte look-up tables, evaluation classes) cleared before each repeat.

    python benchmarks/bench_oracle.py [--n-blocks 5] [--repeats 9]
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import oracle_graph as og  # noqa: E402


def clear_caches():
    for value in vars(og).values():
        if hasattr(value, "cache_clear"):
            value.cache_clear()


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-blocks", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()

    times, search = [], []
    for _ in range(args.repeats):
        clear_caches()
        t = time.perf_counter()
        graph = og.OracleGraph(args.n_blocks)
        times.append(time.perf_counter() - t)
        t = time.perf_counter()
        og._search_classes(args.n_blocks)  # the search alone, tables warm
        search.append(time.perf_counter() - t)
    g = graph
    print(f"{args.n_blocks} blocks: {g.n_classes} classes, {g.n_nodes:,} nodes, {g.n_edges:,} directed edges")
    print(f"  build from scratch   median {statistics.median(times) * 1e3:7.1f} ms   (min {min(times) * 1e3:.1f})")
    print(f"  class search alone   median {statistics.median(search) * 1e3:7.1f} ms")


if __name__ == "__main__":
    main()
