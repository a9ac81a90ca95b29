#!/usr/bin/env bash
# Trains the model shipped in the package (roadgrip/estimators/default_model.pt) and records how, beside it.
# The default is the learned model that generalizes best in `roadgrip evaluate --benchmark generalization` (docs/RESULTS.md):
# trained on the generalization benchmark's training runs, its 90 % intervals calibrated on the benchmark's held-out
# calibration runs. Those runs now carry every production-terminal effect (ProductionEffects.production(): speed from
# the wheels, accelerometer bias/mounting/pitch, grade, worn tires of unknown radius and stiffness); the shipped model was
# trained before they existed (its default_model.json: code_version). `scripts/train_default_model.sh convlstm production`
# trains the candidate on the `production` feature set (roadgrip/features/production.py, no use of the reported speed as
# a slip reference); docs/RESULTS.md ("The shipped default model") has why it is not shipped yet.
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-convlstm}
features=${2:-physics}
roadgrip simulate --preset generalization-train --seed 0 --out build/generalization-train --overwrite
roadgrip simulate --preset generalization-calibration --seed 0 --out build/generalization-calibration --overwrite
cmd=(roadgrip train --model "$model" --features "$features" --data build/generalization-train
     --calibration build/generalization-calibration --stride 2 --batch-size 256 --max-epochs 60 --patience 10 --seed 0
     --out roadgrip/estimators/default_model.pt)
start=$(date +%s)
"${cmd[@]}"
python - "${cmd[*]}" "$(( $(date +%s) - start ))" <<'PY'
import json, sys
import torch
payload = torch.load("roadgrip/estimators/default_model.pt", weights_only=True)
meta = payload["meta"]
record = {
    "model": payload["model"], "feature_set": meta["feature_set"], "window": meta["window"],
    "trained_by": "scripts/train_default_model.sh",
    "data": "roadgrip simulate --preset generalization-train --seed 0 (and generalization-calibration for the intervals); "
            "every production-terminal effect on (roadgrip/sim/production.py)",
    "command": sys.argv[1], "train_wall_s": int(sys.argv[2]), "training": meta["training"], "interval": meta["interval"],
}
open("roadgrip/estimators/default_model.json", "w").write(json.dumps(record, indent=2) + "\n")
PY
echo "default model written: roadgrip/estimators/default_model.pt (+ .json)"
