"""
Is a high half-cheetah return a run or a flip? MPC episodes of saved agents with the torso's pitch recorded.

Planners on the half-cheetah sometimes find that the cheetah moves fastest on its back; such episodes score far above
upright running and make the spread over seeds bimodal. For each model and start seed this prints the MPC return and
the share of steps with the torso pitch beyond ±90° (upside down) and the net full turns of the torso, from
``qpos[2]`` of the MuJoCo state.

    python benchmarks/diagnosis/cheetah_posture.py --env sb3_poplin/PETSCheetah-v0 --models a.zip b.zip --seeds 1000 1001

``--record FILE`` also appends each result to a JSON-lines file with the date, the command and the repository's
commit, and ``--tag KEY=VALUE`` adds fields to those lines (which run, which column, which seed). ``--set KEY=VALUE``
loads the agents with settings that replace the saved ones (``population_size=500 num_elites=50``: the trained agent
planning at another budget than it was trained with; a misspelt setting is an error, ``POPLIN.load``'s).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

from sb3_poplin import POPLIN
from sb3_poplin.analysis.model_error import mpc_episode
from sb3_poplin.tasks import make_env

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import code_version


def upside_down_share(pitches: np.ndarray) -> float:
    """:return: the share of pitches (rad, accumulated over full turns) that point the torso's top downwards"""
    wrapped = np.angle(np.exp(1j * np.asarray(pitches, dtype=np.float64)))  # to (-pi, pi]
    return float(np.mean(np.abs(wrapped) > np.pi / 2))


def net_turns(pitches: np.ndarray) -> float:
    """
    :param pitches: the torso's pitch (rad, accumulated over full turns) along an episode, its start first
    :return: the signed number of full turns from the first pitch to the last (the sign is the ``rooty`` joint's
        axis); a gait that keeps somersaulting has a large ``|turns|``, one that rolls onto its back and stays there
        about half a turn
    """
    pitches = np.asarray(pitches, dtype=np.float64)
    return float((pitches[-1] - pitches[0]) / (2 * np.pi))


def pitch_index(env: gym.Env) -> int:
    """
    :return: where the torso's pitch (``qpos[2]``, joint ``rooty``) sits in the env's observation, which is
        ``qpos[k:]`` then ``qvel`` (HalfCheetah-v5 drops x: ``k = 1``; PETSCheetah keeps its slot: ``k = 0``)
    """
    mj_model = env.unwrapped.model
    if mj_model.nq < 3 or mj_model.joint(2).name != "rooty":
        raise ValueError(
            f"{env.spec.id if env.spec else env}: joint 2 is not 'rooty': this check needs a planar pitch joint (half-cheetah)"
        )
    obs, _ = env.reset(seed=0)
    index = 2 - (mj_model.nq + mj_model.nv - obs.shape[0])
    if not 0 <= index < obs.shape[0] or obs[index] != env.unwrapped.data.qpos[2]:
        raise ValueError(f"the observation of {env.spec.id if env.spec else env} is not qpos[k:] followed by qvel")
    return index


def posture_episode(model: POPLIN, env: gym.Env, seed: int, steps: int, pitch: int) -> dict[str, float]:
    """
    One MPC episode (:func:`sb3_poplin.analysis.model_error.mpc_episode`, as ``diagnose_mpc.py`` plans).

    :param pitch: the pitch's index in the observation (:func:`pitch_index` of ``env``)
    :return: the MPC return, the share of steps upside down (``|pitch| > pi/2``), the largest ``|pitch|`` (rad) and
        the net full turns (:func:`net_turns`)
    """
    episode = mpc_episode(model.mpc, env, steps, seed)
    pitches = episode.obs[1:, pitch]  # after each step
    return {
        "return": float(episode.rewards.sum()),
        "upside_down": upside_down_share(pitches),
        "max_abs_pitch": float(np.max(np.abs(pitches))),
        "turns": net_turns(episode.obs[:, pitch]),  # from the start
    }


INTEGER_TAGS = ("seed",)  # recorded as numbers, as the lines' own seeds are (a commit such as 1234567 stays text)


def split_pairs(items: list[str], option: str, example: str, empty_value: bool = True) -> list[tuple[str, str]]:
    """
    :param items: ``KEY=VALUE`` strings (a value may hold ``=``: only the first one splits)
    :param option: the command-line option they came from, for the error
    :param example: a correct ``KEY=VALUE`` for the error
    :param empty_value: whether ``KEY=`` (an empty value) is allowed
    :return: the (key, value) pairs; a clear error for any other spelling
    """
    pairs = []
    for item in items:
        key, separator, value = item.partition("=")
        if not separator or not key or not (value or empty_value):
            raise SystemExit(f"{option} takes KEY=VALUE, e.g. {option} {example}; got {item!r}")
        pairs.append((key, value))
    return pairs


def parse_tags(tags: list[str]) -> dict[str, str | int]:
    """
    :return: ``KEY=VALUE`` strings as a mapping, the values of :data:`INTEGER_TAGS` as integers (``seed=1`` is
        recorded as ``1``, not ``"1"``); a clear error for any other spelling
    """
    parsed: dict[str, str | int] = {}
    for key, value in split_pairs(tags, "--tag", "column=PETS"):
        if key in INTEGER_TAGS:
            try:
                parsed[key] = int(value)
            except ValueError:
                raise SystemExit(f"--tag {key}= takes an integer (e.g. {key}=1); got {value!r}") from None
        else:
            parsed[key] = value
    return parsed


def parse_settings(given: list[str]) -> dict[str, int | float | str]:
    """
    :return: ``KEY=VALUE`` strings as the keywords of ``POPLIN.load`` (settings that replace the saved ones, e.g.
        ``population_size=500``): a value is an integer, else a float, else text; a clear error for ``KEY`` alone
    """
    parsed: dict[str, int | float | str] = {}
    for key, value in split_pairs(given, "--set", "population_size=500", empty_value=False):
        for kind in (int, float):
            try:
                parsed[key] = kind(value)
                break
            except ValueError:
                continue
        else:
            parsed[key] = value
    return parsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", required=True, help="a half-cheetah task id (HalfCheetah-v5, sb3_poplin/PETSCheetah-v0)")
    parser.add_argument("--models", nargs="+", required=True, help="saved POPLIN zips")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1000])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--record", type=Path, help="a JSON-lines file to append each result to")
    parser.add_argument("--tag", nargs="*", default=[], metavar="KEY=VALUE", help="fields added to the recorded lines")
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="settings that replace the saved ones when the agents are loaded (e.g. population_size=500 num_elites=50: "
        "the trained agent planning at another budget); recorded in each line's 'settings'",
    )
    args = parser.parse_args()
    tags = parse_tags(args.tag)
    settings = parse_settings(args.set)
    if tags and args.record is None:
        raise SystemExit("--tag adds fields to the lines of --record FILE: give --record too")
    provenance = {
        "date": datetime.date.today().isoformat(),
        "command": shlex.join(["python", "benchmarks/diagnosis/cheetah_posture.py", *sys.argv[1:]]),
        "code": code_version(),
    }
    th.set_num_threads(args.threads)
    env = make_env(args.env)
    pitch = pitch_index(env)  # once, and before loading any model: it resets the env
    for path in args.models:
        model = POPLIN.load(path, device="cpu", **settings)
        for seed in args.seeds:
            result = posture_episode(model, env, seed, args.steps, pitch)
            print(json.dumps({"model": path, "seed": seed, "settings": settings, **result}), flush=True)
            if args.record is not None:
                line = {**tags, "model": path, "start_seed": seed, "settings": settings, **result, **provenance}
                with open(args.record, "a") as file:
                    file.write(json.dumps(line) + "\n")


if __name__ == "__main__":
    main()
