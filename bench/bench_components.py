"""Measure the real components on this machine (the paper's Fig. 5 numbers for this platform).

    .venv/bin/python bench/bench_components.py [runs]
"""

import sys

from autopower.chains import profile_components


def main() -> None:
    runs = int(sys.argv[1]) if len(sys.argv) > 1 else 50
    print(f"{'component':<10}{'mean ms':>10}{'median ms':>11}{'max ms':>9}{'in B':>9}{'out B':>8}")
    for name, p in profile_components(runs).items():
        print(f"{name:<10}{p['latency_mean_s'] * 1e3:>10.2f}{p['latency_median_s'] * 1e3:>11.2f}"
              f"{p['latency_max_s'] * 1e3:>9.2f}{p['input_bytes']:>9}{p['output_bytes']:>8}")


if __name__ == "__main__":
    main()
