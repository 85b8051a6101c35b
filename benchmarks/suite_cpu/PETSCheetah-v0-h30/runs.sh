#!/usr/bin/env bash
# Issue 45: the paper's Cheetah to 50k steps at horizon 30 (population 200, 20 elites, 5 CEM iterations, the CPU
# preset's model), runs that survive interruptions. Each column runs from a clone pinned at PIN, in its own virtualenv,
# with its log folder outside the repository's work tree (ROOT, default /root/h45), so that code changes never reach
# a half-finished run and a re-created work tree loses no checkpoint.
#
#   benchmarks/suite_cpu/PETSCheetah-v0-h30/runs.sh start COLUMN   # (re)start a column in the background; resumes
#   benchmarks/suite_cpu/PETSCheetah-v0-h30/runs.sh sync            # the runs' small files and latest checkpoints here
#   benchmarks/suite_cpu/PETSCheetah-v0-h30/runs.sh restore COLUMN  # what start restores first (ROOT lacks a run)
#   benchmarks/suite_cpu/PETSCheetah-v0-h30/runs.sh report COLUMN   # the column's report from what exists
#   benchmarks/suite_cpu/PETSCheetah-v0-h30/runs.sh posture         # the posture check of each complete run's final
#                                                                    # agent not in posture.jsonl yet (~5 min a run)
#   benchmarks/suite_cpu/PETSCheetah-v0-h30/runs.sh status
#
# COLUMN: headline (PETS and POPLIN-P Sep/Avg, seeds 0-3; its report has the baselines too), baselines (SAC and TD3
# to 3 x 50k, in the headline's log folder), bc (POPLIN-P Sep with
# BC and init_var 0.03, seeds 0-1), replan (POPLIN-A Replan, seeds 0-1). On a new machine, `start` first restores the
# runs committed here: complete ones from their small files (and their final agent, carried into carry/.../final/ for
# the posture check), unfinished ones from their small files and the latest checkpoint that `sync` carried into
# carry/ (a new session may get a new machine: the runs of 5d8f6a0 were lost so).
set -euo pipefail

PIN=6f0e1cf  # the runs' code: never moved while a column is unfinished (5d8f6a0's runs were lost with their machine)
ROOT=${H45_ROOT:-/root/h45}  # outside /work, which a new session may lay anew
HERE=$(cd "$(dirname "$0")" && pwd)
REPO=$(git -C "$HERE" rev-parse --show-toplevel)
TREE=$ROOT/tree
VENV=$ROOT/venv
PY=$VENV/bin/python
TASK=sb3_poplin/PETSCheetah-v0
BUDGET=(horizon:30 cem_iterations:5 buffer_size:50000)

column_args() {  # COLUMN [report]: ARGS, and FOLDER (the log folder's name: the baselines share the headline's)
    local algos seeds extra=()
    FOLDER=$1
    case "$1" in
        headline) algos=(pets poplin-p); seeds=(0 1 2 3)
            if [ "${2:-}" = report ]; then algos+=(sac td3); extra=(--steps-scale sac:3 td3:3); fi ;;
        baselines) algos=(sac td3); seeds=(0 1 2 3); extra=(--steps-scale sac:3 td3:3); FOLDER=headline ;;
        bc) algos=(poplin-p); seeds=(0 1); extra=(--params poplin-p:distillation:bc poplin-p:init_var:0.03) ;;
        replan) algos=(poplin-a); seeds=(0 1); extra=(--params poplin-a:proposal:replan) ;;
        *) echo "unknown column $1: headline, baselines, bc or replan" >&2; exit 2 ;;
    esac
    local params=()
    for algo in "${algos[@]}"; do
        case "$algo" in sac|td3) ;; *) for setting in "${BUDGET[@]}"; do params+=("$algo:$setting"); done ;; esac
    done
    # --params collects every ALGO:KEY:VALUE after it: the column's own come last
    local given=()
    if [ "${#extra[@]}" -gt 0 ] && [ "${extra[0]}" = --params ]; then given=("${extra[@]:1}"); extra=(); fi
    ARGS=(--budget cpu --envs "$TASK" --algos "${algos[@]}" --seeds "${seeds[@]}" -n 50000 --eval-freq 25000
          --eval-episodes 2 --policy-eval-freq 5000 --log-folder "$ROOT/logs/$FOLDER" --output "$ROOT/report/$1"
          "${extra[@]}")
    if [ "${#params[@]}" -gt 0 ] || [ "${#given[@]}" -gt 0 ]; then ARGS+=(--params "${params[@]}" "${given[@]}"); fi
}

setup() {
    mkdir -p "$ROOT"
    [ -d "$TREE/.git" ] || git clone -q "$REPO" "$TREE"
    git -C "$TREE" fetch -q "$REPO" 2>/dev/null || true
    git -C "$TREE" checkout -q "$PIN"
    if [ ! -x "$PY" ]; then
        python3 -m venv "$VENV"
        "$PY" -m pip install -q "torch==2.13.0"
        "$PY" -m pip install -q -e "$TREE[extra]"
    fi
}

restore() {  # runs committed here, on a machine that lacks them: complete ones, and unfinished ones with a carry
    local column=$1 folder relative target step
    [ -d "$HERE/$column/zoo" ] || return 0
    for marker in "$HERE/$column"/zoo/*/*/compare_complete.json; do
        [ -e "$marker" ] || continue
        folder=$(dirname "$marker")
        target=$ROOT/logs/$column/${folder#"$HERE/$column/zoo/"}
        [ -d "$target" ] || { mkdir -p "$(dirname "$target")"; cp -r "$folder" "$target"; }
        for final in "$HERE/carry/$column/${folder#"$HERE/$column/zoo/"}"/final/*.zip; do  # its final agent
            if [ -e "$final" ] && [ ! -e "$target/$(basename "$final")" ]; then cp -p "$final" "$target/"; fi
        done
    done
    for step in "$HERE/carry/$column"/*/*/step-*; do  # carry/<column>/<algo>/<run>/step-N
        [ -d "$step" ] || continue
        relative=${step#"$HERE/carry/$column/"}; relative=$(dirname "$relative")
        target=$ROOT/logs/$column/$relative
        [ -d "$target" ] && continue
        mkdir -p "$target/checkpoints"
        cp -r "$HERE/$column/zoo/$relative/." "$target/"
        cp -r "$step" "$target/checkpoints/"
        echo "restored $relative at $(basename "$step") from the carry"
    done
}

carry() {  # the latest checkpoint of every unfinished run into carry/; a complete run's final agent (for the posture
    local logs=$1 column run relative latest final  # check of the final agents) instead of its checkpoint
    column=$(basename "$logs")
    for run in "$logs"*/*/; do
        run=${run%/}; relative=${run#"$logs"}
        if [ -e "$run/compare_complete.json" ]; then
            rm -rf "$HERE/carry/$column/$relative"/step-*
            final=$run/$(basename "$(dirname "$TASK")")-$(basename "$TASK").zip  # the zoo's <env name>.zip
            if [ -e "$final" ] && [ ! -e "$HERE/carry/$column/$relative/final/$(basename "$final")" ]; then
                mkdir -p "$HERE/carry/$column/$relative/final"; cp -p "$final" "$HERE/carry/$column/$relative/final/"
            fi
            continue
        fi
        latest=$(ls "$run/checkpoints" 2>/dev/null | grep -E '^step-[0-9]+$' | sort -t- -k2 -n | tail -1 || true)
        if [ -z "$latest" ]; then
            rm -rf "$HERE/carry/$column/$relative"; continue
        fi
        [ -d "$HERE/carry/$column/$relative/$latest" ] && continue
        rm -rf "$HERE/carry/$column/$relative"; mkdir -p "$HERE/carry/$column/$relative"
        cp -rp "$run/checkpoints/$latest" "$HERE/carry/$column/$relative/"
    done
}

case "${1:-}" in
    start)
        column_args "$2"; setup; restore "$FOLDER"
        mkdir -p "$ROOT/logs/$FOLDER"
        (cd "$TREE" && nohup "$PY" benchmarks/compare.py "${ARGS[@]}" --jobs "${JOBS:-2}" \
            >> "$ROOT/logs/$2.out" 2>&1 &)
        echo "started $2: $ROOT/logs/$2.out" ;;
    restore)  # what `start` restores first, alone
        column_args "$2"; restore "$FOLDER" ;;
    sync)
        for logs in "$ROOT"/logs/*/; do  # logs/<folder>/ -> <folder>/zoo/
            column=$(basename "$logs")
            (cd "$logs" && find . -path '*/checkpoints' -prune -o -path './compare_logs' -prune -o -type f \
                \( -name '*.csv' -o -name '*.npz' -o -name '*.yml' -o -name '*.txt' -o -name '*.json' \) -print) |
            while read -r file; do
                mkdir -p "$HERE/$column/zoo/$(dirname "$file")"
                cp -p "$logs/$file" "$HERE/$column/zoo/$file"
            done
            [ -n "${NO_CARRY:-}" ] || carry "$logs"  # NO_CARRY=1: the small files only (the carry at the stop)
        done ;;
    report)
        column_args "$2" report
        # the issue's table: the paper's protocol at 15k, 25k, 35k and 50k steps, each seed's value too; runs not
        # finished yet are in it as far as they got (their small files, synced)
        (cd "$REPO" && "$REPO/.venv/bin/python" benchmarks/compare.py "${ARGS[@]}" --report-only --include-unfinished \
            --protocol-steps 15000 25000 35000 50000 --log-folder "$HERE/$FOLDER/zoo" --output "$HERE/$2") || true
        # beside the paper's Table 1: each column against the paper's mean ± std (Welch's test), POPLIN-P / PETS with
        # an exact permutation test, and the posture check of every final agent (posture.jsonl)
        [ -e "$HERE/$2/results.json" ] && (cd "$REPO" && "$REPO/.venv/bin/python" benchmarks/diagnosis/beside_paper.py \
            --report "$HERE/$2" --paper POPLIN-P=12228,5653 POPLIN-A=4651,1089 PETS=4205,789 SAC=1746,839 TD3=219,593 \
            --paper-seeds 4 --ratio POPLIN-P PETS --posture "$HERE/posture.jsonl" --write --note "Wang & Ba 2019, \
Table 1 (PETS's Cheetah, 50 000 steps, horizon 30, 4 seeds; the same measure). The paper's planner had a population \
of 500 and a 5 × 4×200 model; these runs have 200 (20 elites, 5 iterations) and the CPU preset's 5 × 3×128 (issue 45).")
        ;;
    posture)  # with the repository's code (the agents were trained by PIN), one 1000-step MPC episode from seed 1000
        for marker in "$ROOT"/logs/*/*/*/compare_complete.json; do
            [ -e "$marker" ] || continue
            run=$(dirname "$marker"); relative=${run#"$ROOT/logs/"}; relative=${relative#*/}  # <algo>/<run>
            final=$run/$(basename "$(dirname "$TASK")")-$(basename "$TASK").zip
            [ -e "$final" ] || { echo "$relative: no final agent, skipped" >&2; continue; }
            grep -qF "\"run\": \"$relative\"" "$HERE/posture.jsonl" 2>/dev/null && continue
            read -r column seed < <("$REPO/.venv/bin/python" -c 'import json, sys
job = json.load(open(sys.argv[1]))["job"]  # e.g. poplin-p_sb3_poplin-PETSCheetah-v0_seed0
print(job.split("_")[0].upper(), job.rsplit("_seed", 1)[1])' "$marker")
            echo "posture of $column seed $seed ($relative)"
            (cd "$REPO" && "$REPO/.venv/bin/python" benchmarks/diagnosis/cheetah_posture.py --env "$TASK" \
                --models "$final" --seeds 1000 --record "$HERE/posture.jsonl" \
                --tag "column=$column" "seed=$seed" "run=$relative" "trained_by=$PIN")
        done ;;
    status)
        pgrep -af "sb3_poplin(.experiments)?.zoo train" | sed 's/ -params.*//' || echo "no run is training"
        for log in "$ROOT"/logs/*/compare_logs/*.log; do
            [ -e "$log" ] && printf '%s: %s\n' "$(basename "$log" .log)" "$(grep -c '' "$log") lines"
        done ;;
    *) sed -n 2,15p "$0"; exit 2 ;;
esac
