"""Bags with compressed chunks (the recorder's ``compression``: zstd by default, or none; lz4,
the format's other compression, as another recorder writes it): the readers of the project
(read_messages, replay, show), bag repair and the mcap library's own reader take them as they
take uncompressed ones."""
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from exit_decision_msgs.msg import CavCommand, CavCommandArray
from mcap.reader import make_reader
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader

from exit_decision.cli import main
from exit_decision.ros.bags.storage import COMPRESSIONS, open_writer, read_messages, typestore
from exit_decision.ros.topics import COMMANDS_TOPIC

TESTS = Path(__file__).resolve().parent
FIXTURE = TESTS / 'fixtures' / 'replay_bag'


def chunk_compressions(bag: Path) -> set[str]:
    """The compression each chunk of the bag's mcap file names ('' for none)."""
    with open(next(bag.glob('*.mcap')), 'rb') as file:
        return {index.compression for index in make_reader(file).get_summary().chunk_indexes}


def writer_of(bag: Path, compression: str):
    """An open writer at ``bag``: the project's, or for lz4 rosbags' with its mcap chunks
    compressed so (as rosbag2's mcap plugin can write them)."""
    if compression != 'lz4':
        return open_writer(bag, compression)
    from lz4.frame import compress
    writer = open_writer(bag)
    writer.storage.compression, writer.storage.compressor = 'lz4', compress
    return writer


def recompress(source: Path, target: Path, compression: str) -> None:
    """The messages of bag ``source`` in a new bag at ``target`` with this chunk compression."""
    store = typestore()
    with Reader(source) as reader:
        writer = writer_of(target, compression)
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store,
                                                   offered_qos_profiles=c.ext.offered_qos_profiles)
                       for c in reader.connections}
        for connection, timestamp, raw in reader.messages():
            writer.write(connections[connection.id], timestamp, raw)
        writer.close()


def commands(step: int) -> bytes:
    msg = CavCommandArray(step=step, commands=[CavCommand(vehicle_id=f'CAV_{i}') for i in range(40)])
    return serialize_message(msg)


@pytest.mark.parametrize('compression', [*COMPRESSIONS, 'lz4'])
def test_a_bag_is_written_with_the_compression_asked_and_reads_back_whole(tmp_path, compression):
    bag = tmp_path / 'bag'
    writer = writer_of(bag, compression)
    connection = writer.add_connection(COMMANDS_TOPIC, 'exit_decision_msgs/msg/CavCommandArray', typestore=typestore())
    for step in range(2000):
        writer.write(connection, 1_000_000_000 + step, commands(step))
    writer.close()
    assert chunk_compressions(bag) == {'' if compression == 'none' else compression}
    assert [msg.step for _, _, _, msg in read_messages(bag)] == list(range(2000))
    with open(bag / 'bag.mcap', 'rb') as file:   # Foxglove's reader too
        assert sum(1 for _ in make_reader(file).iter_messages()) == 2000
    size = (bag / 'bag.mcap').stat().st_size
    assert size < 400_000 if compression != 'none' else size > 1_000_000, size


def test_an_unknown_compression_is_refused():
    for other in ('gzip', 'lz4'):
        with pytest.raises(ValueError, match=re.escape(f"compression {other!r}; allowed: none | zstd")):
            open_writer(Path('/nonexistent/bag'), other)


KILLED_WRITER = textwrap.dedent('''
    import os, sys
    from pathlib import Path
    from exit_decision_msgs.msg import CavCommand, CavCommandArray
    from rclpy.serialization import serialize_message
    from exit_decision.ros.bags.storage import typestore
    from exit_decision.ros.nodes.recorder import flush
    from test_bag_compression import writer_of
    writer = writer_of(Path(sys.argv[1]), sys.argv[2])
    connection = writer.add_connection('/exit_decision/cav_commands', 'exit_decision_msgs/msg/CavCommandArray',
                                       typestore=typestore())
    for step in range(3000):
        msg = CavCommandArray(step=step, commands=[CavCommand(vehicle_id=f'CAV_{i}') for i in range(40)])
        writer.write(connection, 1_000_000_000 + step, serialize_message(msg))
        if step % 1000 == 999:
            flush(writer)   # what the recorder does once a second
    os._exit(9)   # no close: what SIGKILL leaves
''')


@pytest.mark.parametrize('compression', ['zstd', 'lz4'])
def test_a_killed_compressed_recording_is_repaired_compressed(tmp_path, capsys, compression):
    bag = tmp_path / 'bag'
    subprocess.run([sys.executable, '-c', KILLED_WRITER, str(bag), compression], check=False,
                   env={**os.environ, 'PYTHONPATH': os.pathsep.join([str(TESTS), str(TESTS.parent)])})
    assert main(['bag', 'repair', str(bag)]) == 0
    assert 'recovered 3000 messages' in capsys.readouterr().out
    assert [msg.step for _, _, _, msg in read_messages(bag)] == list(range(3000))
    assert chunk_compressions(bag) == {'zstd'}, 'the recording\'s compression, zstd for one the recorder does not write'


@pytest.fixture(scope='module')
def compressed_fixtures(tmp_path_factory):
    """The replay fixture (a bag the stack recorded, uncompressed) with zstd and lz4 chunks."""
    made = {}
    for compression in ('zstd', 'lz4'):
        target = tmp_path_factory.mktemp(compression) / 'replay_bag'
        target.mkdir()
        shutil.copy(FIXTURE / 'override.yaml', target / 'override.yaml')
        recompress(FIXTURE / 'bag', target / 'bag', compression)
        assert chunk_compressions(target / 'bag') == {compression}
        made[compression] = target
    return made


@pytest.mark.parametrize('compression', ['zstd', 'lz4'])
def test_replay_decides_a_compressed_bag_as_the_uncompressed_one(compressed_fixtures, compression):
    from exit_decision.ros.bags.replay import check_fixture
    plain, packed = check_fixture(FIXTURE), check_fixture(compressed_fixtures[compression])
    # whether the replay reproduces the recording is test_replay_fixture's: here, the same report
    assert packed.commands > 0 and (packed.summary(limit=0), packed.differences) == (plain.summary(limit=0),
                                                                                     plain.differences)


def test_show_draws_a_compressed_bag(compressed_fixtures, tmp_path, capsys):
    bag = compressed_fixtures['zstd'] / 'bag'
    out = tmp_path / 'show'
    assert main(['show', str(bag), '--episode', '0', '--start', '0', '--end', '1', '--out', str(out)]) == 0
    assert 'episode 0: ' in capsys.readouterr().out
    assert (out / 'episode_0_time_space.png').is_file()
