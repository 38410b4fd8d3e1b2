"""Print the ARX [2 2 3] hair-dryer reference (MathWorks dryer2 protocol).

Run: .venv/bin/python experiments/hair_dryer/arx_223.py
"""

import numpy as np
from load import load_dryer

from greybox import blackbox as bb

full = load_dryer()
ze = bb.detrend(full.segment(0, 300))  # samples 1-300
zv = bb.detrend(full.segment(799, 900))  # samples 800-900
m = bb.fit_arx(ze, 2, 2, 3)
np.set_printoptions(precision=4, suppress=True)
print(f"A = {m.a[0]}   B = {m.b[0, 0]}   (std errors {m.std_errors[0]})")
for label, d in (("estimation 1-300", ze), ("validation 800-900", zv)):
    sim = bb.compare(m, d).fit_percent[0]
    one = bb.compare(m, d, k=1).fit_percent[0]
    print(f"{label}: simulation fit {sim:.1f} %   one-step fit {one:.1f} %")
