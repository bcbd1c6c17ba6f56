"""The build worker's heap settings (nuplan_occ.pipeline.memory): a freed frame-sized block is reused
without faulting its pages in again."""

import platform
import resource

import numpy as np
import pytest

from nuplan_occ.pipeline.memory import MMAP_THRESHOLD_BYTES, release_free_memory, reuse_freed_pages

glibc_only = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the settings are glibc's")


def _faults_of_filling(n_bytes: int) -> int:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = np.ones(n_bytes, dtype=np.uint8)  # malloc, then every page written
    del block
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


@glibc_only
def test_a_freed_flow_sized_block_is_refilled_without_page_faults():
    assert reuse_freed_pages()
    n_bytes = 40 << 20  # above glibc's largest adaptive mmap threshold (32 MB): mapped afresh by default
    assert n_bytes < MMAP_THRESHOLD_BYTES
    _faults_of_filling(n_bytes)
    assert _faults_of_filling(n_bytes) < 50  # by default: 10240 pages of 4 KB, or 20 huge pages and ~500 others


@glibc_only
def test_release_returns_the_free_heap_so_the_next_fill_faults_again():
    assert reuse_freed_pages()
    n_bytes = 40 << 20
    _faults_of_filling(n_bytes)
    assert release_free_memory()
    assert _faults_of_filling(n_bytes) >= (n_bytes >> 21)  # one per 2 MB huge page at least
