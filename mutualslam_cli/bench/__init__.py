"""``make bench``: the speed figures of DESIGN §10 and the benchmarks of the VO, the BA and a fine-tuning step."""
