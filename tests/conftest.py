"""Test-session setup: under pytest-xdist each worker gets one torch thread, so two workers
on a two-core machine do not oversubscribe it (the trainer itself defaults to one thread)."""

import os

import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
