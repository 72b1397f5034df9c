#!/bin/bash
# docs/decisions.md S33: the camera-order check on a wrong trace, and one camera traced.
# Run in an empty work folder with jaxcr importable:
#   bash $REPO/experiments/stereo/warnings_s33/run.sh
# Development seeds only (real_like 4000-4199; never 4200 and above).
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
A=$HERE/../issue16_audit_r31
python $A/render.py 4000 4005 4010                                # rl_SEED.pkl
for seed in 4000 4005; do
  python $A/build.py $seed d$seed
  # 1. two cameras, right order and swapped order: each camera_order_check call's inputs
  for s in s_entry s_cams_swapped; do
    (cd d$seed/$s && python $HERE/dump_order.py . -o $PWD/../../r${seed}_$s --no-overlays)
  done
  python $A/score.py r${seed}_s_entry d$seed/truth.json
  # 2. one camera, the default (auto -> trace)
  (cd d$seed/s_one_cam && jaxcr stereo . -o $PWD/../../r${seed}_one --no-overlays)
  python $A/score.py r${seed}_one d$seed/truth.json
done
python $A/build.py 4010 d4010                                   # one camera only
(cd d4010/s_one_cam && jaxcr stereo . -o $PWD/../../r4010_one --no-overlays)
python $A/score.py r4010_one d4010/truth.json
python $HERE/recheck_order.py r*_order.pkl                      # before / after the S33 rule
# 3. single-view signals of the trace on both views of seeds 4000-4015 vs the true tip
python $HERE/single_view_stats.py $(seq 4000 4015) > sv_stats.jsonl
# 4. true tips' distance to the image border and projected lengths, 400 views, no rendering
python $HERE/true_tip_edges.py 4000 4199
