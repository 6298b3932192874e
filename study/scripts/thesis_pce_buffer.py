"""The thesis' ME-PCE (``world_model=pce_thesis``) fitted on a run's own real data: held-out error
against the samples required per term and the number of elements.

    python study/scripts/thesis_pce_buffer.py <run dir or checkpoint.pt of a pce_thesis run>
        [--divisions 1 7] [--oversampling 2 5 10 20] [--order 3]

Takes the replay buffer a model-based run's checkpoint carries (the policy's episodes, with the
memory columns of ``world_model=pce_thesis``), and fits it with ``ClosedFormTrainer`` as training does
(the model and trainer built as training builds them, ``world_model_setup.configured``; 20% of the
transitions held out) for every (divisions, oversampling): the trainer's reported
held-out error is the standardised MSE of the predicted state (1 = no better than each output's
mean over the data), which for this model is its open-loop error.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

# The benchmarks' world-model setup and buffer reader, which this study script builds on.
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import world_model_setup as setup  # noqa: E402
from branch_accuracy import buffer_of  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("--divisions", type=int, nargs="+", default=[1, 7])
    parser.add_argument("--oversampling", type=float, nargs="+", default=[2.0, 5.0, 10.0, 20.0])
    parser.add_argument("--order", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    data = buffer_of(args.run)
    probe = setup.make_model("pce_thesis")
    if data["state"].shape[-1] != probe.layout.size:
        raise ValueError(f"{args.run}: its buffer's states have {data['state'].shape[-1]} columns, a pce_thesis "
                         f"run's have {probe.layout.size} (the thesis state and its memory)")
    print(f"{len(data)} real transitions ({len(data) // 100} episodes); order {args.order}, T = 3")
    print("| elements | samples per term | terms fitted (widest) | held-out error | training error | fit s |")
    print("|---|---|---|---|---|---|")
    for divisions in args.divisions:
        for oversampling in args.oversampling:
            model, trainer = setup.configured("pce_thesis", overrides=(
                f"world_model.model.order={args.order}", f"world_model.model.divisions={divisions}",
                f"world_model.trainer.oversampling={oversampling}"))
            report = trainer.fit(model, data, torch.Generator().manual_seed(0))
            print(f"| {divisions}x{divisions} | {oversampling:g} | {model.fitted_terms} | "
                  f"{float(report.validation_error[0]):.3f} | {report.train_loss:.3f} | {report.seconds:.1f} |")


if __name__ == "__main__":
    main()
