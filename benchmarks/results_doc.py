"""Write docs/results.md and docs/results/*.png from the sweeps made by benchmarks/results.sh.

    python benchmarks/results_doc.py sweeps        # SWEEPS directory of results.sh

Each env has a sweep directory per configuration: ENV-softac (softac's preset), ENV-softac-NAME (another preset or
options), ENV-PEER (a peer of softac.peers.PEERS: ENV-sbx, ENV-sb3, ENV-sbx-crossq, ENV-sbx-crossq-softac); the
threshold of each is the one given to its sweep command (kept in results.sh). Tables and figures come from the
trial run directories alone, and name each configuration by its preset and framework. The MuJoCo suite also gets
one aggregate over its five envs: the interquartile mean of normalised final scores with stratified-bootstrap 95%
intervals (rliable's). An env none of whose sweeps is in SWEEPS keeps its section of the current
docs/results.md (the aggregate too), so the classic and the MuJoCo sets can be regenerated apart.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from softac.base.cpus import machine_description

# the page sections' modules sit beside this script (also when a test loads it by its path); AGAINST_BEST,
# machines_of, short_machines, wall_ratio and published_means are imported for the tests, which read them here
sys.path.insert(0, str(Path(__file__).resolve().parent))

from results_common import (AGAINST_BEST, AGGREGATE, DMC, ENVS, FRONT, SUITE, SUITE_V4,  # noqa: E402
                            machines_of, short_machines, wall_ratio)
from results_dmc import dmc_section  # noqa: E402
from results_mujoco import averaging_pairs, front, published_means, section, suite_aggregate  # noqa: E402
from results_offline import offline_section  # noqa: E402
from results_pixels import pixels_section  # noqa: E402
from results_playground import playground_section  # noqa: E402


INTRO = """# Results: softac beside SBX and Stable-Baselines3 on the same machine

Made with `softac sweep` (Ray Tune, one trial per CPU, two trials at a time, each trial's process pinned
to its CPU); each env's section names the machine its sweeps ran on (this page was last written on
{machine}). Every framework is evaluated the same way: every `eval_interval` steps, 10 episodes with
deterministic actions, episode i seeded `seed + 1000000 + i`.

- Classic set (InvertedPendulum-v5/v4, Pusher-v5): softac's env presets on 5 seeds, Stable-Baselines3's
  SAC at its defaults on 3 seeds (`softac sweep --framework sb3`), the same step budget. Issue 43's classic
  set (Pendulum-v1, MountainCarContinuous-v0, LunarLanderContinuous-v3, BipedalWalker-v3): softac's env
  presets on seeds 0-4 (their settings were chosen on seeds 100 and up) beside Stable-Baselines3's SAC at RL
  Zoo's tuned settings for each env (`--framework sb3-zoo`, 3 seeds), RL Zoo's step budget; "reached R" is
  the solved return (-200, 90, 200, 300).
- MuJoCo suite (HalfCheetah, Hopper, Walker2d, Ant, Humanoid, all v5): 100k env steps. "softac, crossq
  preset" is softac's env preset (each extends `crossq` and changes nothing else), on 5 seeds; beside it,
  like for like, "SBX CrossQ, crossq preset's settings" (`softac sweep --framework sbx-crossq-softac`: SBX's
  CrossQ at the same settings, 2 seeds); "SBX CrossQ, its defaults" (`--framework sbx-crossq`: 1024-wide
  critics, batch 256; hours a run on one CPU, so only where finished); "SBX SAC, its defaults" (2 seeds).
  softac multiplies in bf16 where the CPU has it (`matmul_dtype: auto`), SBX in float32. Stable-Baselines3
  trains ~3x slower than SBX and is left out of this budget. The aggregate section puts the five envs
  together.
- Goal envs (FetchReach-v4, FetchPush-v4, PointMaze_UMaze-v3; the `[robotics]` extra): softac's env presets
  (SAC with hindsight experience replay) beside Stable-Baselines3's and SBX's SAC with SB3's HerReplayBuffer at
  their defaults (`--framework sb3-her`, `sbx-her`: future, 4 goals, learning_starts 1000), 20 deterministic
  episodes an evaluation; their tables add the final success rate and the steps until it first reached 0.9, and a second
  figure draws the success rates.
- Other rows, on the same seeds and budget: "softac, NAME preset" is another preset on the env (`results.sh
  options`: plain SAC, `sac-100k`, beside the CrossQ presets; `results.sh fallback`: `default` and
  `crossq` on envs with no preset of their own); "... + KEY=VALUE" adds options to it.
- Wall times are comparable between trials run at the same time on the same machine (its speed drifts by
  up to 2x between days): each trial's `config.yaml` records when it started (`segments`), and the notes
  below say which trials ran side by side.

Columns:
- final eval: the last evaluation of each trial (mean ± std over seeds, and the 95% Student-t interval);
  final IQM: its interquartile mean over seeds (rliable's; the plain mean below 4 seeds);
- best eval: the best evaluation of each trial;
- median wall s: the whole trial's training time, evaluations included, over the trials whose wall time is
  comparable (those in benchmarks/sweeps/timing-excluded.yaml, listed under the aggregate, are left out of
  it; their returns count); steps/s: steps over that time;
- reached R (classic set): trials whose evaluation reached the threshold R at least once, with the
  median steps and seconds (training wall time, evaluations included) until the first time.

Regenerate (rerunning continues where it stopped; `results.sh Hopper-v5` runs one env, `results.sh mujoco`
the suite):

```sh
make bench
SOFTAC=.venv/bin/softac bash benchmarks/results.sh      # sweeps in benchmarks/sweeps
.venv/bin/python benchmarks/results_doc.py benchmarks/sweeps
```

The sweep commands, from `benchmarks/results.sh` ($1 is the env id):

```sh
{commands}
```
"""


def kept_sections(results_md: Path) -> dict[str, list[str]]:
    """The `## ENV` sections (and the aggregate's) of an existing results.md, by heading."""
    if not results_md.exists():
        return {}
    sections: dict[str, list[str]] = {}
    current: str | None = None
    for line in results_md.read_text().splitlines():
        if line.startswith("## "):
            heading = line[3:].strip()
            current = heading if heading in ENVS or heading in (AGGREGATE, FRONT, DMC) else None
            if current:
                sections[current] = []
        if current:
            sections[current].append(line)
    return sections


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sweeps", type=Path)
    p.add_argument("--docs", type=Path, default=Path(__file__).resolve().parent.parent / "docs")
    a = p.parse_args(argv)
    figures = a.docs / "results"
    figures.mkdir(parents=True, exist_ok=True)
    script = (Path(__file__).parent / "results.sh").read_text().splitlines()
    commands = "\n".join(line.strip() for line in script if "$SOFTAC sweep" in line)
    kept = kept_sections(a.docs / "results.md")
    text = [INTRO.format(machine=machine_description(), commands=commands)]
    for env, threshold in ENVS.items():
        if env == SUITE[0]:
            text.extend(suite_aggregate(a.sweeps, figures, kept))
        if env == SUITE_V4[0]:
            text.extend(front(a.sweeps, figures, kept))
        text.extend(section(env, threshold, a.sweeps, figures, kept))
    text.extend(dmc_section(a.sweeps, kept, figures))
    text.extend(averaging_pairs(a.sweeps))
    text.extend(pixels_section(a.sweeps))
    text.extend(playground_section(a.sweeps))
    text.extend(offline_section(a.sweeps))
    notes = a.docs / "results-notes.md"
    if notes.exists():
        text.append(notes.read_text())
    (a.docs / "results.md").write_text("\n".join(text))
    print(json.dumps({"wrote": str(a.docs / "results.md")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
