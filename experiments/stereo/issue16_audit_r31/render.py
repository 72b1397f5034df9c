"""Render real_like frames (jaxcr.synth.real_like, 1280x720) to rl_SEED.pkl in the working folder
(issue 16 audit r31): python render.py 5000 5001 5002 (development seeds >= 5000 only)."""

import pickle
import sys
import time

from jaxcr.synth.real_like import render_real_like_frame

for seed in map(int, sys.argv[1:]):
    t = time.time()
    f = render_real_like_frame(seed)
    with open(f"rl_{seed}.pkl", "wb") as fh:
        pickle.dump(f, fh)
    print(seed, time.time() - t, flush=True)
