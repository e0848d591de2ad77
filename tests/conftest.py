"""Test-session setup: the library computes in float64 (``latentforce.enable_x64``), which
importing it no longer switches on by itself."""

import latentforce

latentforce.enable_x64()
