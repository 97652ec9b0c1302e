import os
import sys

# Tests run on the CPU; two host devices let sharding code be exercised.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(__file__))
