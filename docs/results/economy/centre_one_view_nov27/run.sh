#!/bin/bash
# The probe of "One view a step for the centre prompt alone" (docs/results/economy/README.md):
# apply one_view.patch to the code of 2026-11-27 (d8265f5), then run 3DGS and the centre prompt
# interleaved by seed: tumbler 1/4 and fern 1/2, 1500 steps, six seeds. The patch is not in the
# code (not adopted). The mountain pair: the same bench on the 16-sample `small` mountain, seed 0,
# with and without the patch.
for s in 0 1 2 3 4 5; do
  for m in 3dgs promptgs-center; do
    promptgs bench --scene tumbler=../shared/data/tumbler@images_4 --methods $m --iterations 1500 --seeds $s --out runs/one/tumbler
  done
done
for s in 0 1 2 3 4 5; do
  for m in 3dgs promptgs-center; do
    promptgs bench --grid docs/results/proposals/grid_fern.json --methods $m --iterations 1500 --seeds $s --out runs/one/fern
  done
done
