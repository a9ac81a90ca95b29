#!/usr/bin/env bash
# Trains the model shipped in the package (roadgrip/estimators/default_model.pt) and records how, beside it.
# The default is the learned model that generalizes best in `roadgrip evaluate --benchmark generalization` (docs/RESULTS.md):
# trained exactly as there, on the generalization benchmark's training runs, its 90 % intervals calibrated on the
# benchmark's held-out calibration runs.
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-convlstm}
features=${2:-physics}
roadgrip simulate --preset generalization-train --seed 0 --out build/generalization-train --overwrite
roadgrip simulate --preset generalization-calibration --seed 0 --out build/generalization-calibration --overwrite
cmd=(roadgrip train --model "$model" --features "$features" --data build/generalization-train
     --calibration build/generalization-calibration --stride 2 --batch-size 256 --max-epochs 60 --patience 10 --seed 0
     --out roadgrip/estimators/default_model.pt)
"${cmd[@]}"
python - "${cmd[*]}" <<'PY'
import json, sys
import torch
payload = torch.load("roadgrip/estimators/default_model.pt", weights_only=True)
meta = payload["meta"]
record = {
    "model": payload["model"], "feature_set": meta["feature_set"], "window": meta["window"],
    "trained_by": "scripts/train_default_model.sh",
    "data": "roadgrip simulate --preset generalization-train --seed 0 (and generalization-calibration for the intervals)",
    "command": sys.argv[1], "training": meta["training"], "interval": meta["interval"],
}
open("roadgrip/estimators/default_model.json", "w").write(json.dumps(record, indent=2) + "\n")
PY
echo "default model written: roadgrip/estimators/default_model.pt (+ .json)"
