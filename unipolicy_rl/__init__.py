"""unipolicy_rl: one TRPO locomotion policy for a robot whose build is uncertain, on TorchRL."""

__version__ = "0.1.0"
