#!/usr/bin/env bash
# Trains the model shipped in the package (roadgrip/estimators/default_model.pt) and records how, beside it.
set -euo pipefail
cd "$(dirname "$0")/.."
data=build/paper-seed0
roadgrip simulate --preset paper --seed 0 --out "$data" --overwrite
cmd=(roadgrip train --model sa-cnn-lstm --data "$data" --experiment 1 --features terminal --seed 0
     --out roadgrip/estimators/default_model.pt)
"${cmd[@]}"
python - "${cmd[*]}" <<'PY'
import json, sys
import torch
meta = torch.load("roadgrip/estimators/default_model.pt", weights_only=True)["meta"]
record = {
    "model": "sa-cnn-lstm", "feature_set": meta["feature_set"], "window": meta["window"],
    "trained_by": "scripts/train_default_model.sh",
    "data": "roadgrip simulate --preset paper --seed 0 (experiment 1 runs only: experiment 2 stays unseen)",
    "command": sys.argv[1], "training": meta["training"], "interval": meta["interval"],
}
open("roadgrip/estimators/default_model.json", "w").write(json.dumps(record, indent=2) + "\n")
PY
echo "default model written: roadgrip/estimators/default_model.pt (+ .json)"
