"""The bank export beyond one machine, as docs/user_guide.md tells it: a Ray cluster of
several nodes (``ray start --head``, ``ray start --address`` per other node; here
separate processes on this machine sharing its output folder) running
``export_bank.py --executor ray --address``, and the array-job recipe (``--shard i/n``
processes into one folder, then ``--assemble``). Both give the single-process bank's
bytes."""

import subprocess
import sys

import pytest

from pgt_blender import dev
from pgt_blender.core.bank.folder import prepare_folder, read_identity
from pgt_blender.core.errors import InputError

from .test_bank import SCRIPT, bank_bytes, objects, prepared, reference, run_export  # noqa: F401 (fixtures)


@pytest.fixture
def cluster():
    """(head address, driver environment, node folders) of a head and one worker node,
    one CPU each; stopped after the test, failed or not."""
    pytest.importorskip("ray")
    with dev.local_ray_cluster((1, 1)) as started:
        yield started


def test_a_ray_cluster_of_two_nodes_exports_the_single_process_bank(cluster, reference, prepared, tmp_path):
    address, env, nodes = cluster
    out, config = reference
    result = run_export("--objects", prepared, "--config", config, "--out", tmp_path / "bank", "--executor", "ray",
                        "--address", address, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    chunks = len(list((out / ".work" / "chunks").glob("*.json")))
    ran = dev.ray_tasks_per_node(nodes)
    assert sum(ran) == chunks and min(ran) > 0, f"chunks run per node: {ran} of {chunks}"
    assert bank_bytes(tmp_path / "bank") == bank_bytes(out)


def test_array_job_shards_into_one_folder_assemble_to_the_single_process_bank(reference, prepared, tmp_path):
    """The user guide's array job: every --shard i/n at once (as a scheduler starts them),
    into one shared folder, then one --assemble."""
    out, config = reference
    shared = tmp_path / "bank"
    shards = [subprocess.Popen([sys.executable, str(SCRIPT), "--objects", str(prepared), "--config", str(config),
                                "--out", str(shared), "--shard", f"{index}/2", "--workers", "1"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for index in range(2)]
    for shard in shards:
        stdout, stderr = shard.communicate(timeout=300)
        assert shard.returncode == 0, stderr
        assert f"--assemble --out {shared}" in stdout
    assert not (shared / "manifest.json").exists()
    run_export("--assemble", "--out", shared, check=True)
    assert bank_bytes(shared) == bank_bytes(out)


def test_shards_starting_together_share_the_folder_another_is_making(tmp_path):
    """Array tasks start at once: a shard that finds the folder being made by another
    (.work/chunks there, that shard's identity still a temporary) writes the same
    identity beside it and removes nothing; a shard of other settings is refused."""
    ident = {"config": {"seed": 0}, "objects": ["truck"], "class_names": ["truck"], "chunks": 4}
    out = tmp_path / "bank"
    (out / ".work" / "chunks").mkdir(parents=True)
    other = out / ".work" / ".identity.json.otherhost-1.partial"
    other.write_bytes(b'{"conf')
    prepare_folder(out, ident, resume=False, overwrite=False, shared=True)
    assert read_identity(out) == ident and other.read_bytes() == b'{"conf'
    prepare_folder(out, ident, resume=False, overwrite=False, shared=True)  # the next shard joins
    with pytest.raises(InputError, match="other objects or settings"):
        prepare_folder(out, {**ident, "chunks": 5}, resume=False, overwrite=False, shared=True)
