#!/bin/bash
# The GPU checks of one device session, as one call: the CUDA tests, a step's profile and operator trace
# (this tree's code, and with BASE another tree's, e.g. `git archive HEAD~3 delta | tar -x -C .base`),
# losses and gradients on CUDA against the CPU with step times, and the held-out PSNR along a stage 1 at
# the capture's size. Everything it writes goes to OUT; each part has its own time limit, so a slow part
# costs its own figures only.
#
#   SUBJECT=results/synthetic/tight BODY=resources/body/anny_sub1.npz OUT=/tmp/gpu bash benchmarks/device_checks.sh
#
# SUBJECT holds frames.h5, init/params.npz and stage1/settings.json (a stage 1 started by the workflow);
# CURVE (JSON settings over the run's) and STEPS choose the held-out curve's variant; BASE is a folder
# holding another tree's delta/; PYTHONPATH may name wheels installed beside the machine's own packages.
# Run from the repository's root.
set -u
: "${SUBJECT:?the folder of the subject results}" "${BODY:?the body model npz}" "${OUT:?a folder for the results}"
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}  # this tree's delta, where nothing is installed
CURVE=${CURVE:-'{"nerf": {"levels": 6, "max_res": 192}, "albedo": {"levels": 6, "max_res": 192}, "render": {"samples": 32}, "stage1": {"iterations": 2000, "rays": 8192, "plateau_window": 0}}'}
STEPS=${STEPS:-500,1000,2000}
export PYTHONUNBUFFERED=1
S=$SUBJECT/stage1/settings.json
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$OUT/gpu.txt"
python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name())" | tee -a "$OUT/gpu.txt"
timeout 150 python3 -m pytest -q -n 0 -p no:cacheprovider tests/geometry tests/deformers/test_round_trip.py \
    tests/body/test_lbs.py tests/synthetic/test_cameras.py 2>&1 | tail -15 | tee "$OUT/tests.txt"
for code in current ${BASE:+base}; do
    TREE=$PWD
    [ "$code" = base ] && TREE=$(cd "$BASE" && pwd)
    PYTHONPATH=$TREE${PYTHONPATH:+:$PYTHONPATH} timeout 120 python3 benchmarks/step_profile.py --settings "$S" --init "$SUBJECT/init/params.npz" \
        --record "$SUBJECT/frames.h5" --body "$BODY" --device cuda --threads 8 --steps 20 \
        --out "$OUT/profile_$code.csv" --trace "$OUT/trace_$code.csv" 2>&1 | tail -14
done
timeout 180 python3 benchmarks/cuda_check.py --record "$SUBJECT/frames.h5" --body "$BODY" --init "$SUBJECT/init/params.npz" \
    --settings "$S" --label "$(basename "$SUBJECT"), its stage-1 settings" --steps 30 --cpu-threads 2 \
    --out "$OUT/cuda_check.csv" 2>&1 | tail -30
timeout 330 python3 benchmarks/held_out_curve.py --settings "$S" --record "$SUBJECT/frames.h5" --body "$BODY" \
    --init "$SUBJECT/init/params.npz" --subject "$(basename "$SUBJECT")" --perceptual "" --device cuda --threads 8 \
    --override "$CURVE" --label "$CURVE" --steps "$STEPS" --out /tmp/held_out_curve --csv "$OUT/held_out_curve.csv" 2>&1 | tail -12
