#!/bin/bash
# docs/decisions.md S32: jaxcr stereo --segmentation auto. Run in an empty work folder with
# jaxcr importable: bash $REPO/experiments/stereo/auto_s32/run.sh
# Development seeds only: real_like 4000-4005 (never 4200 and above), stereo synth 0-2.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
A=$HERE/../issue16_audit_r31
# 1. The tutorial's step 2 on real_like rigs (1280x720), no segmentation flag.
python $A/render.py 4000 4001 4002 4003 4004 4005            # rl_SEED.pkl, ~1 min each
for seed in 4000 4001 4002 4003 4004 4005; do
  python $A/build.py $seed d$seed
  (cd d$seed/s_entry && jaxcr stereo . -o runs/stereo)
  python $A/score.py d$seed/s_entry/runs/stereo d$seed/truth.json
done
# 2. One camera, the chroma key on a real background: the WARNING (audit r31 S18).
jaxcr stereo d4000/s_one_cam -o runs/one_chroma --segmentation chroma
# 3. Clean chroma synth sets: chroma against the new default (trace: the sets have plates).
for s in 0 1 2; do
  jaxcr stereo synth -o syn_g$s --frames 3 --size 640x480 --seed $s
  jaxcr stereo synth -o syn_b$s --frames 3 --size 640x480 --seed $s --background blue
done
jaxcr stereo synth -o syn4 --frames 3 --size 320x240 --seed 4
for s in syn4 syn_g0 syn_g1 syn_g2 syn_b0; do
  jaxcr stereo $s -o runs_clean/${s}_chroma --segmentation chroma --no-overlays
  jaxcr stereo $s -o runs_clean/${s}_auto --no-overlays
  python $HERE/backbone_vs_truth.py $s runs_clean/${s}_chroma runs_clean/${s}_auto
done
# 4. The key check's statistics.
python $HERE/key_stats.py syn4 syn_g0 syn_g1 syn_g2 syn_b0 syn_b1 syn_b2 rl_400[0-5].pkl
