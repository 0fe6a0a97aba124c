"""Test vectors for posediff-metrics' re-creation of numpy's legacy global RNG as test.py uses it:
`np.random.seed(seed)` once, then `np.random.choice(n, k, replace=False)` per sequence.

    python3 scripts/make_numpy_choice_vectors.py > fixtures/numpy/legacy_choice.json
"""
import json

import numpy as np

cases = []
for seed, calls in [
    (0, [(20, 10), (16, 10), (11, 10), (50, 10), (202, 10), (1000, 10), (3, 3), (10, 1)]),
    (1, [(100, 10), (100, 10), (7, 5)]),
    (42, [(70000, 10), (2, 2), (65537, 3)]),
    (4294967295, [(1, 1), (30, 30), (1 << 20, 4)]),
]:
    np.random.seed(seed)
    out = [np.random.choice(n, k, replace=False).tolist() for n, k in calls]
    cases.append({"seed": seed, "calls": [[n, k] for n, k in calls], "choices": out})
# Raw 32-bit outputs after seeding, to check the generator itself.
np.random.seed(0)
raw = np.random.randint(0, 2**32, size=8, dtype=np.uint64).tolist()
print(json.dumps({"numpy": np.__version__, "choice_cases": cases, "seed0_first_uint32": raw}, indent=1))
