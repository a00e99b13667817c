import torch

# The suite is made of small batched tensor ops, for which one intra-op thread is fastest and
# keeps timings steady on a shared 2-core machine.
torch.set_num_threads(1)
