"""Benchmarks and independent references (CasADi IPOPT / FATROP); needs ``pip install torchtraj[bench]``."""
