import torch

# Two cores on CI: one thread per process keeps tests from oversubscribing.
torch.set_num_threads(1)
