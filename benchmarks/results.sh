#!/usr/bin/env bash
# Regenerates the sweeps behind docs/results.md, one trial per CPU (each trial pinned), same evaluation for
# every framework (10 deterministic episodes every eval_interval steps).
#   classic: InvertedPendulum-v5/v4 and Pusher-v5, softac's presets on 5 seeds, Stable-Baselines3 on 3; issue 43's
#            classic set (Pendulum-v1, MountainCarContinuous-v0; the [box2d] extra's LunarLanderContinuous-v3,
#            BipedalWalker-v3): softac's presets on seeds 0-4 (tuned on seeds 100+), SB3's SAC at RL Zoo's tuned
#            settings on 3 (--framework sb3-zoo), RL Zoo's step budget, steps and seconds to the solved return
#   mujoco:  HalfCheetah, Hopper, Walker2d, Ant, Humanoid (v5), 100k steps: softac's env presets (CrossQ) on 5
#            seeds; SBX's CrossQ at the same settings (sbx-crossq-softac: the crossq preset's) on 2; SBX's SAC at its
#            defaults on 2 (SB3 trains ~3x slower than SBX here: not within the budget)
#   crossq-defaults: SBX's CrossQ at its own defaults (1024-wide critics, batch 256), 2 seeds, on Hopper-v5 and
#            Walker2d-v5 (about 2 hours a trial on one CPU; crossq-defaults:ENV for one env)
#   crossq-wn: issue 30's step past CrossQ, the crossq preset with weight normalisation (`--set weight_norm=true`;
#            the crossq-wn preset of that time) on 5 seeds per suite env, the crossq preset's budget (crossq-wn:ENV for
#            one env). Issue 42 made `crossq-wn` CrossQ+WN at its published settings (front)
#   front:   issue 42's front on Gym MuJoCo v4 (the published tables' version), 100k steps: the crossq preset, and
#            the SAC family at the published settings where a run fits in about 2 hours of one core (crossq-wn),
#            else at the largest settings that do (TQC with SBX's size, SimBa with 128-wide critic blocks, DroQ at
#            5 updates per step), beside SBX at the same settings (front:ENV for one env)
#   dmc:     issue 43's DeepMind Control Suite tasks (the [dmc] extra) at 100k frames: 50k agent steps with
#            action repeat 2, the crossq preset (= the dmc preset), 5 seeds; and a task's own preset (dmc-TASK) where
#            it has one (dmc:TASK for one task)
#   dmc500k: issue 43's three tasks continued to 500k frames (cheetah-run, walker-run, quadruped-run; 250k agent
#            steps, an evaluation every 20k frames), the same settings, 1 seed (dmc500k:TASK for one task)
#   options: goal 4 of issue #18, the option from the literature against plain SAC on the same seeds and
#            budget: the env presets are CrossQ (Bhatt et al. 2024), so this runs plain SAC's settings
#            (`--preset sac-100k`, the presets before CrossQ) beside them (options:ENV for one env)
#   pixels:  issue 44 from pixels on a CPU (48x48 frames, batch 32): DMC cartpole-swingup with the drq preset at
#            action repeat 8 and 100k frames (3 seeds), InvertedPendulum-v5 with its preset beside SB3's CnnPolicy (2 seeds)
#   robotics: issue 31's goal envs (the [robotics] extra): softac's presets (SAC + HER) beside SB3's and SBX's SAC + HER
#            at their defaults (sb3-her, sbx-her), 20 deterministic episodes an evaluation (robotics:ENV for one env)
#   fallback: goal 1 of issue #18, envs with no preset of their own (Swimmer, Reacher, InvertedDoublePendulum):
#            the `default` preset beside `crossq` and SBX, 100k steps
# Usage: bash benchmarks/results.sh [classic|mujoco|options|fallback|crossq-defaults|crossq-wn|front|dmc|dmc500k|pixels|robotics|ENV|options:ENV ...]   (default: classic mujoco)
# Needs the [ray] and [bench] extras (make bench). Rerunning continues where it stopped (finished trials are
# not redone). Then: python benchmarks/results_doc.py $SWEEPS
# SWEEPS defaults to benchmarks/sweeps, where git keeps each finished trial's logs (config.yaml, eval.csv,
# progress.csv, episodes.csv, summary.json; .gitignore leaves out weights, TensorBoard files and Ray's state),
# so later sessions add seeds and envs to the same tables. Each trial's config.yaml names its machine.
set -euo pipefail
SOFTAC=${SOFTAC:-.venv/bin/softac}
SWEEPS=${SWEEPS:-benchmarks/sweeps}
MUJOCO="HalfCheetah-v5 Hopper-v5 Walker2d-v5 Ant-v5 Humanoid-v5"
MUJOCO_V4="Hopper-v4 Ant-v4 HalfCheetah-v4 Walker2d-v4 Humanoid-v4"
CLASSIC="InvertedPendulum-v5 InvertedPendulum-v4 Pusher-v5 Pendulum-v1 MountainCarContinuous-v0 LunarLanderContinuous-v3 BipedalWalker-v3"
FALLBACK="Swimmer-v5 Reacher-v5 InvertedDoublePendulum-v5"
ROBOTICS="FetchReach-v4 FetchPush-v4 PointMaze_UMaze-v3"
DMC="cheetah-run walker-run quadruped-run finger-spin reacher-hard walker-walk cartpole-swingup hopper-hop"
DMC_500K="cheetah-run walker-run quadruped-run"

classic() {
  case $1 in
    InvertedPendulum-v5|InvertedPendulum-v4)
      $SOFTAC sweep --env $1 --seeds 5 --steps 20000 --threshold 1000 --out $SWEEPS/$1-softac
      $SOFTAC sweep --env $1 --seeds 3 --steps 20000 --threshold 1000 --framework sb3 --out $SWEEPS/$1-sb3 ;;
    Pusher-v5)
      $SOFTAC sweep --env $1 --seeds 5 --steps 30000 --threshold -40 --out $SWEEPS/$1-softac
      $SOFTAC sweep --env $1 --seeds 3 --steps 30000 --threshold -40 --framework sb3 --out $SWEEPS/$1-sb3 ;;
    Pendulum-v1|MountainCarContinuous-v0|LunarLanderContinuous-v3|BipedalWalker-v3)
      local steps threshold stop=()
      case $1 in
        Pendulum-v1) steps=20000; threshold=-200 ;;
        MountainCarContinuous-v0) steps=50000; threshold=90 ;;
        # RL Zoo's 500k-step budgets take SB3 ~2.5 h a seed here: each trial stops once solved (the table's
        # figure is the steps and seconds to solve; its final eval is then the solving one)
        LunarLanderContinuous-v3) steps=500000; threshold=200; stop=(--target-return=200) ;;
        BipedalWalker-v3) steps=500000; threshold=300; stop=(--target-return=300) ;;
      esac
      $SOFTAC sweep --env $1 --seeds 5 --steps $steps --threshold $threshold "${stop[@]}" --out $SWEEPS/$1-softac
      $SOFTAC sweep --env $1 --seeds 3 --steps $steps --threshold $threshold "${stop[@]}" --framework sb3-zoo --out $SWEEPS/$1-sb3-zoo ;;
  esac
}

mujoco() {
  # the env presets are the crossq preset (extends: crossq, nothing else); the sweeps began as --preset crossq
  $SOFTAC sweep --env $1 --seeds 5 --steps 100000 --preset crossq --out $SWEEPS/$1-softac
  $SOFTAC sweep --env $1 --seeds 2 --steps 100000 --framework sbx-crossq-softac --set eval_interval=5000 --out $SWEEPS/$1-sbx-crossq-softac
  $SOFTAC sweep --env $1 --seeds 2 --steps 100000 --framework sbx --set eval_interval=5000 --out $SWEEPS/$1-sbx
}

crossq_defaults() {
  $SOFTAC sweep --env $1 --seeds 2 --steps 100000 --framework sbx-crossq --set eval_interval=5000 --out $SWEEPS/$1-sbx-crossq
}

crossq_wn() {
  $SOFTAC sweep --env $1 --seeds 5 --steps 100000 --preset crossq --set weight_norm=true --out $SWEEPS/$1-softac-crossq-wn
}

front() {
  local tqc=(--preset tqc --set n_critics=2 critic_hidden_sizes=256,256)
  local simba=(--preset simba --set critic_hidden_sizes=128,128 log_std_mode=clamp log_std_min=-20)
  $SOFTAC sweep --env $1 --seeds 3 --steps 100000 --preset crossq --out $SWEEPS/$1-softac
  $SOFTAC sweep --env $1 --seeds 3 --steps 100000 --preset crossq-wn --out $SWEEPS/$1-softac-crossq-wn-published
  $SOFTAC sweep --env $1 --seeds 3 --steps 100000 "${tqc[@]}" --out $SWEEPS/$1-softac-tqc-2x256
  $SOFTAC sweep --env $1 --seeds 2 --steps 100000 --framework sbx-tqc-softac "${tqc[@]}" --out $SWEEPS/$1-sbx-tqc-softac
  $SOFTAC sweep --env $1 --seeds 3 --steps 100000 "${simba[@]}" --out $SWEEPS/$1-softac-simba-128
  $SOFTAC sweep --env $1 --seeds 2 --steps 100000 --framework sbx-simba-softac "${simba[@]}" --out $SWEEPS/$1-sbx-simba-softac
  $SOFTAC sweep --env $1 --seeds 3 --steps 100000 --preset droq --set gradient_steps=5 policy_delay=5 --out $SWEEPS/$1-softac-droq-utd5
}

dmc() {
  $SOFTAC sweep --env dmc:$1 --seeds 5 --steps 50000 --preset crossq --set action_repeat=2 --out $SWEEPS/dmc-$1-softac-crossq-ar2
  # a task with a preset of its own (dmc-TASK, chosen on seeds 100-102: benchmarks/screens) runs it on seeds 0-4 too
  if [ -f src/softac/config/presets/dmc-$1.yaml ]; then
    $SOFTAC sweep --env dmc:$1 --seeds 5 --steps 50000 --preset dmc-$1 --out $SWEEPS/dmc-$1-softac-dmc-$1
  fi
}

dmc500k() {
  $SOFTAC sweep --env dmc:$1 --seeds 1 --steps 250000 --preset crossq --set action_repeat=2 eval_interval=10000 --out $SWEEPS/dmc-$1-softac-crossq-ar2-500k
}

pixels() {
  # issue 44 on a CPU: an update at 84x84 takes 0.3-6 s on one core (hours a run), at 48x48 and batch 32 40-70 ms
  # on an AMD EPYC core (docs/performance.md), so these runs use 48x48 frames and batch 32. cartpole-swingup: the
  # drq preset (DrQ's settings) at DrQ's PlaNet setting, action repeat 8, 100k frames = 12,500 agent steps (pixels at
  # [0, 1]; dmc-cartpole-swingup-softac-drq-48px holds the runs from before pixel_range, at [-0.5, 0.5]).
  # InvertedPendulum-v5: its own preset from pixels with target_encoder (chosen on tuning seed 100,
  # benchmarks/screens), up to 50k steps or the first evaluation of 1000, beside SB3's CnnPolicy on the same frames
  # (benchmarks/sb3_pixels.py), which stops there too
  $SOFTAC sweep --env dmc:cartpole-swingup --seeds 3 --steps 12500 --preset drq \
    --set action_repeat=8 pixel_size=48 batch_size=32 eval_interval=1250 --out $SWEEPS/pixels/dmc-cartpole-swingup-softac-drq-48px-unit
  $SOFTAC sweep --env InvertedPendulum-v5 --seeds 2 --steps 50000 --threshold 1000 --target-return=1000 \
    --set pixels=true pixel_size=48 batch_size=32 target_encoder=true --out $SWEEPS/pixels/InvertedPendulum-v5-softac-48px
  for seed in 0 1; do
    "$(dirname "$SOFTAC")/python" benchmarks/sb3_pixels.py --env InvertedPendulum-v5 --steps 50000 --seed $seed \
      --pixel-size 48 --eval-interval 1000 --eval-episodes 10 --threads 1 --target-return 1000 \
      --out $SWEEPS/pixels/InvertedPendulum-v5-sb3-cnn-48px/seed=$seed
  done
}

options() {
  # plain SAC, the env presets' settings before CrossQ
  $SOFTAC sweep --env $1 --seeds 3 --steps 100000 --preset sac-100k --out $SWEEPS/$1-softac-sac-100k
}

fallback() {
  $SOFTAC sweep --env $1 --seeds 3 --steps 100000 --preset default --out $SWEEPS/$1-softac-default
  $SOFTAC sweep --env $1 --seeds 3 --steps 100000 --preset crossq --out $SWEEPS/$1-softac-crossq
  $SOFTAC sweep --env $1 --seeds 2 --steps 100000 --framework sbx --set eval_interval=5000 --out $SWEEPS/$1-sbx
}

robotics() {
  local steps evals=(--set eval_episodes=20)
  case $1 in
    FetchReach-v4) steps=10000; evals=(--set eval_interval=1000 eval_episodes=20) ;;
    FetchPush-v4) steps=300000; evals=(--set eval_interval=10000 eval_episodes=20) ;;
    PointMaze_UMaze-v3) steps=50000; evals=(--set eval_interval=2500 eval_episodes=20) ;;
  esac
  $SOFTAC sweep --env $1 --seeds 5 --steps $steps "${evals[@]}" --out $SWEEPS/$1-softac
  $SOFTAC sweep --env $1 --seeds 3 --steps $steps --framework sb3-her "${evals[@]}" --out $SWEEPS/$1-sb3-her
  $SOFTAC sweep --env $1 --seeds 3 --steps $steps --framework sbx-her "${evals[@]}" --out $SWEEPS/$1-sbx-her
}

targets=${*:-classic mujoco}
for target in $targets; do
  case $target in
    classic) for env in $CLASSIC; do classic $env; done ;;
    mujoco) for env in $MUJOCO; do mujoco $env; done ;;
    options) for env in $MUJOCO; do options $env; done ;;
    options:*) options ${target#options:} ;;
    crossq-defaults) for env in Hopper-v5 Walker2d-v5; do crossq_defaults $env; done ;;
    crossq-defaults:*) crossq_defaults ${target#crossq-defaults:} ;;
    crossq-wn) for env in $MUJOCO; do crossq_wn $env; done ;;
    front) for env in $MUJOCO_V4; do front $env; done ;;
    front:*) front ${target#front:} ;;
    crossq-wn:*) crossq_wn ${target#crossq-wn:} ;;
    fallback) for env in $FALLBACK; do fallback $env; done ;;
    robotics) for env in $ROBOTICS; do robotics $env; done ;;
    dmc) for task in $DMC; do dmc $task; done ;;
    dmc:*) dmc ${target#dmc:} ;;
    dmc500k) for task in $DMC_500K; do dmc500k $task; done ;;
    dmc500k:*) dmc500k ${target#dmc500k:} ;;
    pixels) pixels ;;
    robotics:*) robotics ${target#robotics:} ;;
    *) if [[ " $MUJOCO " == *" $target "* ]]; then mujoco $target
       elif [[ " $FALLBACK " == *" $target "* ]]; then fallback $target
       else classic $target; fi ;;
  esac
done
