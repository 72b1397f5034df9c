"""Round 21 (issue 16 item 2, docs/decisions.md S50): the tip step's fold and trim on a pair
whose tips are within the calibration's tolerance and whose backbones explain each other.

Since S37 the tips' re-search acts only on tips further apart than right tips can be under
the rig's calibration error (about 8 px on the real_like preset), while the fold and the
trim act over the fixed 5 px flag: they cut whole backbones that leave over a tube width
unexplained. A right pair 5.5 px apart (dev 4654; each tip within 2 px) was trimmed to 19.5
px. Variants, each :func:`jaxcr.stereo.pipeline.traced_stereo_tips` with
``calibration=REAL_LIKE_CALIBRATION`` on the stored traces (the stored alternatives returned
for ``trace_alternatives``):

* ``ref`` -- as committed before S50 (``mend_within_tolerance=True``);
* ``tolerance`` -- ``mend_within_tolerance=False`` (S50; measured, not adopted): a pair within the tolerance whose
  backbones leave at most ``CONSISTENT_PX`` (40 px) unexplained is neither folded nor
  trimmed; the re-search as before.

    python experiments/segmentation/real_like_tip_mend.py --seeds 4560-4829 \\
        --store STORE --out ROWS
    python experiments/segmentation/real_like_tip_mend.py --summary ROWS.json
"""

from __future__ import annotations

from real_like_tip_gate import evaluate as gate_evaluate
from real_like_tip_gate import summary as gate_summary
from tip_harness import harness_main

VARIANTS = {
    "ref": {"mend_within_tolerance": True},
    "tolerance": {"mend_within_tolerance": False},
}


def main() -> int:
    return harness_main(
        __doc__,
        "/tmp/real_like_tip_mend",
        lambda seeds, store, out: gate_evaluate(seeds, store, out, VARIANTS),
        lambda path: gate_summary(path, VARIANTS),
    )


if __name__ == "__main__":
    raise SystemExit(main())
