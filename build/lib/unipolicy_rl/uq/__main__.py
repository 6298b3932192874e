"""``python -m unipolicy_rl.uq CKPT ...``: the command line of :mod:`unipolicy_rl.uq`."""

from unipolicy_rl.uq import cli

if __name__ == "__main__":
    cli()
