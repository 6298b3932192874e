"""What a padded MLP's slots mean under each token layout: roles per slot over the training robots,
and how much of each held-out robot sits where a training robot had a link of the same role.

    python study/scripts/slot_roles.py [--training 8,16,32]

A link's role is what the structural layout keys its slot on (body segment ``i``; leg pair ``k``,
its side, and the link's place along the leg: ``unipolicy_rl/envs/slot_layout.py``). The split
is the default ``robot=grammar`` one. Per count of training robots (the first N of the split's
training side, as ``robot.training_morphologies``) and layout, it prints the median and largest
number of roles one slot holds over those robots (the structural layout: 1 by construction), and
over the 16 held-out robots the median and smallest share of a robot's links whose slot held a
link of the same role in some training robot: what weights tied to slots can have learnt for it.
"""

from __future__ import annotations

import argparse
import statistics
from collections import defaultdict
from pathlib import Path

from hydra import compose, initialize_config_dir

from unipolicy_rl.env_factories import grammar_morphologies, morphology_env_kwargs
from unipolicy_rl.envs.slot_layout import TOKEN_LAYOUTS
from unipolicy_rl.robots.grammar import describe

CONF = Path(__file__).resolve().parents[1] / "conf"


def link_slots_and_roles(morphologies, layout, roles_layout):
    """Per robot, ``(slot, role)`` of each link: the slot ``layout`` gives it, the role the structural one does."""
    rows = []
    for morphology in morphologies:
        names = [link.name for link in describe(morphology.derivation()).links]
        slots = range(len(names)) if layout is None else layout.slots(names)
        rows.append(list(zip((int(s) for s in slots), (int(r) for r in roles_layout.slots(names)), strict=True)))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--training", default="8,16,32", help="counts of training robots, comma-separated")
    args = parser.parse_args(argv)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        base = compose("config", overrides=["robot=grammar", "robot.token_layout=structural"])
    roles_layout = morphology_env_kwargs(base)["token_layout"]
    split, _ = grammar_morphologies(base, "train")
    print("| training robots | layout | roles per used slot (median / most) | held-out links at a slot "
          "trained on their role (median / least) |")
    print("|---|---|---|---|")
    for count in (int(text) for text in args.training.split(",")):
        for name in TOKEN_LAYOUTS:
            layout = roles_layout if name == "structural" else None
            roles = defaultdict(set)
            for robot in link_slots_and_roles(split.train[:count], layout, roles_layout):
                for slot, role in robot:
                    roles[slot].add(role)
            per_slot = [len(held) for held in roles.values()]
            shares = [sum(role in roles.get(slot, ()) for slot, role in robot) / len(robot)
                      for robot in link_slots_and_roles(split.held_out, layout, roles_layout)]
            print(f"| {count} | {name} | {statistics.median(per_slot):g} / {max(per_slot)} | "
                  f"{statistics.median(shares):.2f} / {min(shares):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
