"""Shared test set-up: one torch thread (fastest on these 2-core machines) and small helpers."""

import torch as th

th.set_num_threads(1)
