#!/usr/bin/env bash
# The SO-101 trunk: one WSD world-model run that goes on across sessions and machines (docs/world_model.md, "The
# trunk"). The cores belong to it: start it in a session's first minutes, pause it around heavy jobs, save its
# travelling state before the session ends.
#
#   scripts/trunk.sh start       resume the trunk detached (its workdir; else the committed state; else v7), on a
#                                frozen copy of HEAD's code outside the tree; collects the SO-101 store first if absent
#   scripts/trunk.sh status      running or paused, its step, windows trained since started, steps/s
#   scripts/trunk.sh pause|continue   SIGSTOP / SIGCONT (scripts/with_trunk_paused CMD does both around CMD)
#   scripts/trunk.sh stop        SIGTERM: it saves a checkpoint at its next step and exits
#   scripts/trunk.sh save        its travelling state (bfloat16 moments) -> $STATE, to commit (the trunk paused)
#   scripts/trunk.sh branch N OUT    anneal a copy of its latest state over N steps, export to OUT (paused)
#
# Environment: RUNS (~/sc3-runs), STATE (exports/so101_trunk: the committed state), FROM (exports/so101_v7_cpu: the
# start when there is neither a workdir nor a state), SEED (5).
set -euo pipefail
REPO="$(cd "$(dirname "$0")/.." && pwd)"
RUNS="${RUNS:-$HOME/sc3-runs}"
SO=$RUNS/so101
WORK=$SO/trunk
STATE="${STATE:-$REPO/exports/so101_trunk}"
FROM="${FROM:-$REPO/exports/so101_v7_cpu}"
PIDFILE=$SO/trunk.pid
LOG=$SO/trunk.log
STARTED=$SO/trunk.started   # the windows the trunk had when `start` ran
VENV="${VENV:-$REPO/.venv}"

running() { [ -f "$PIDFILE" ] && kill -0 "$(cat "$PIDFILE")" 2>/dev/null; }
windows() { python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['windows'])" "$1" 2>/dev/null || echo 0; }

case "${1:-status}" in
start)
  if running; then echo "the trunk is already running (pid $(cat "$PIDFILE")): $LOG"; exit 0; fi
  mkdir -p "$SO"
  # a frozen copy of the committed code (HEAD; uncommitted edits are not run): editing the tree while the trunk
  # trains changes nothing it runs, and its lineage names a commit anyone can check out
  COMMIT="$(git -C "$REPO" rev-parse --short=12 HEAD)"
  CODE=$RUNS/code/$COMMIT
  if [ ! -d "$CODE/sc3_jax" ]; then
    rm -rf "$CODE.tmp" && mkdir -p "$CODE.tmp"
    git -C "$REPO" archive HEAD sc3_jax configs | tar -x -C "$CODE.tmp"
    mv "$CODE.tmp/configs" "$CODE.tmp/sc3_jax/configs"  # where an installed package keeps them
    rm -rf "$CODE" && mv "$CODE.tmp" "$CODE"
  fi
  if [ -f "$WORK/config.json" ]; then  # the workdir's own start and tokenizer: a resume keeps its config
    mapfile -t ORIGIN < <(python3 -c '
import json, sys
c = json.load(open(sys.argv[1]))
for flag, v in (("--model.tokenizer-path", c["model"]["tokenizer_path"]), ("--train.init-from", c["train"]["init_from"]),
                ("--train.resume-from", c["train"].get("resume_from"))):
    if v:
        print(flag); print(v)' "$WORK/config.json")
    WHAT="resumed from its workdir"
  elif [ -f "$STATE/trunk.json" ]; then
    ORIGIN=(--train.resume-from "$STATE" --model.tokenizer-path "$STATE/tokenizer"); WHAT="resumed from $STATE"
  else
    ORIGIN=(--train.init-from "$FROM" --model.tokenizer-path "$FROM/tokenizer"); WHAT="started from $FROM"
  fi
  if [ -f "$WORK/lineage.json" ]; then windows "$WORK/lineage.json" > "$STARTED"
  elif [ -f "$STATE/lineage.json" ] && [ -f "$STATE/trunk.json" ]; then windows "$STATE/lineage.json" > "$STARTED"
  else windows "$FROM/lineage.json" > "$STARTED"; fi
  # the tokenizer the run was started with (a workdir's config.json has it); collect the store only when absent
  SO="$SO" VENV="$VENV" REPO="$REPO" CODE="$CODE" COMMIT="$COMMIT" setsid nohup bash -c '
    set -euo pipefail
    cd "$SO"
    . "$VENV/bin/activate"
    if [ ! -f "$SO/train/dataset.json" ]; then bash "$REPO/docs/so101_curve/collect.sh"; fi
    exec env PYTHONPATH="$CODE" SC3_CODE_COMMIT="$COMMIT" python -m sc3_jax.cli train "$@"
  ' trunk --config so101_latent --model.action-sum pose --data "$SO/train" --batch 12 \
    --train.workdir "$WORK" --train.schedule wsd --train.steps 10000000 --train.warmup-steps 30 \
    --train.ckpt-every 50 --train.log-every 10 --train.no-progress --train.seed "${SEED:-5}" ${ORIGIN[@]+"${ORIGIN[@]}"} \
    >> "$LOG" 2>&1 < /dev/null &
  echo $! > "$PIDFILE"
  echo "trunk $WHAT (pid $(cat "$PIDFILE"), code $CODE): $LOG"
  ;;
status)
  if ! running; then echo "the trunk is not running"; else
    st=$(ps -o stat= -p "$(cat "$PIDFILE")" | head -c1)
    [ "$st" = T ] && echo "the trunk is paused (pid $(cat "$PIDFILE"))" || echo "the trunk is running (pid $(cat "$PIDFILE"))"
  fi
  if [ -f "$WORK/metrics.jsonl" ]; then
    python3 - "$WORK" "$STARTED" <<'EOF'
import json, sys
from pathlib import Path
work, started = Path(sys.argv[1]), Path(sys.argv[2])
rows = [json.loads(l) for l in (work / "metrics.jsonl").read_text().splitlines() if l.strip().endswith("}")]
lin = json.loads((work / "lineage.json").read_text()) if (work / "lineage.json").exists() else {"windows": 0}
batch = json.loads((work / "config.json").read_text())["data"]["batch_size"]
last = rows[-1]
since = int(started.read_text()) if started.exists() else 0
now = lin["windows"] + (last["step"] - lin["stretches"][-1]["to_step"]) * batch if lin.get("stretches") else 0
print(f"step {last['step']}  loss {last['loss']:.4f}  lr {last['lr']:.2e}  {last.get('steps_per_s', 0):.2f} steps/s  "
      f"windows since initialisation {now:,}; trained since `start` {now - since:,}")
EOF
  fi
  ;;
pause) running && kill -STOP -- -"$(cat "$PIDFILE")" && echo "trunk paused" ;;
continue) running && kill -CONT -- -"$(cat "$PIDFILE")" && echo "trunk continued" ;;
stop)
  if running; then
    kill -CONT -- -"$(cat "$PIDFILE")"; kill -TERM "$(cat "$PIDFILE")"
    while running; do sleep 2; done; echo "trunk stopped (its checkpoint saved)"
  fi
  ;;
save)
  "$REPO/scripts/with_trunk_paused" "$VENV/bin/sc3" trunk save --run "$WORK" --out "$STATE"
  ;;
branch)
  N=$2; OUT=$3
  "$REPO/scripts/with_trunk_paused" "$VENV/bin/sc3" trunk branch --trunk "$WORK" --steps "$N" --out "$OUT" --no-progress
  ;;
*) echo "usage: scripts/trunk.sh start|status|pause|continue|stop|save|branch N OUT" >&2; exit 2 ;;
esac
