"""Benchmarks of nuplan-occ, outside the library: each imports `nuplan_occ` as a user would and writes its
report under bench/ (`make bench`, `make bench-scale`, `make bench-manifest`)."""
