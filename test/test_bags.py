"""Bags without running nodes: reading a bag's sequence numbers, gaps, repair of a killed
recording, and `exit-decision replay` / `bag repair` on bags a user may give them."""
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from mcap.reader import make_reader
from exit_decision_msgs.msg import CavCommandArray, TrafficGraph, VehicleStateArray
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from exit_decision.cli import main
from exit_decision.ros.bags.repair import repair_bag
from exit_decision.ros.bags.storage import BagError, read_messages, typestore
from exit_decision.ros.topics import COMMANDS_TOPIC, STATES_TOPIC
from exit_decision.step_gaps import StepGaps, episode_and_step


@pytest.mark.parametrize('frame_id', ['', 'a', 'ab', 'abc', 'abcd', 'fuzz'])
@pytest.mark.parametrize('cls', [VehicleStateArray, TrafficGraph, CavCommandArray])
def test_episode_and_step_are_read_from_the_cdr_rclpy_sends(cls, frame_id):
    msg = cls(episode=7, step=2**32 - 1)
    msg.header.frame_id = frame_id
    assert episode_and_step(serialize_message(msg)) == (7, 2**32 - 1)


def test_step_gaps_count_holes_within_an_episode_only():
    gaps = StepGaps(stride=5)
    missing = [gaps.see(0, step) for step in (0, 5, 10, 30, 35, 20)]   # 15, 20, 25 missing; 20 late
    assert missing == [0, 0, 0, 3, 0, 0] and (gaps.gaps, gaps.missing) == (1, 3)
    assert [gaps.see(1, step) for step in (40, 45)] == [0, 0], 'a new episode may start anywhere'


def write_commands(bag: Path, steps) -> None:
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection(COMMANDS_TOPIC, 'exit_decision_msgs/msg/CavCommandArray',
                                           typestore=typestore())
        for step in steps:
            writer.write(connection, 1_000_000_000 + step, serialize_message(CavCommandArray(step=step)))


KILLED_WRITER = textwrap.dedent('''
    import os, sys
    from pathlib import Path
    from exit_decision_msgs.msg import CavCommand, CavCommandArray
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    from exit_decision.ros.bags.storage import typestore
    writer = Writer(Path(sys.argv[1]), version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    connection = writer.add_connection('/exit_decision/cav_commands', 'exit_decision_msgs/msg/CavCommandArray',
                                       typestore=typestore())
    for step in range(3000):   # about 2.6 MB: two complete chunks, the third one unfinished
        msg = CavCommandArray(step=step, commands=[CavCommand(vehicle_id=f'CAV_{i}') for i in range(40)])
        writer.write(connection, 1_000_000_000 + step, serialize_message(msg))
    writer.storage.bio.write(b'\\x06' + (10**6).to_bytes(8, 'little') + b'cut short')   # a chunk the kill cut
    writer.storage.bio.flush()
    os._exit(9)   # no close: what SIGKILL leaves
''')


def test_a_killed_recording_is_repaired_up_to_its_last_complete_chunk(tmp_path, capsys):
    bag = tmp_path / 'bag'
    subprocess.run([sys.executable, '-c', KILLED_WRITER, str(bag)], check=False)
    assert main(['replay', str(bag)]) == 2
    assert 'unfinished bag' in capsys.readouterr().err
    assert main(['bag', 'repair', str(bag)]) == 0
    out = capsys.readouterr().out
    steps = [msg.step for _, _, _, msg in read_messages(bag)]
    assert 0 < len(steps) < 3000 and steps == list(range(len(steps))), 'every message of the complete chunks'
    assert f'recovered {len(steps)} messages' in out and 'lost: ' in out and 'the last 18 bytes of the file' in out, out
    with Reader(bag) as reader:
        assert reader.message_count == len(steps), 'a finished bag: summary and metadata.yaml'
    with open(bag / 'bag.mcap', 'rb') as file:   # and for the mcap library's own reader (summary, chunk index)
        reader = make_reader(file)
        assert reader.get_summary().statistics.message_count == len(steps)
        assert sum(1 for _ in reader.iter_messages()) == len(steps)
    assert (bag / 'bag.mcap.unfinished').exists(), 'the unfinished file is kept'
    with pytest.raises(BagError, match='nothing to repair'):
        repair_bag(bag)


def bad_bag(tmp_path: Path, kind: str) -> Path:
    bag = tmp_path / 'bag'
    if kind == 'empty directory':
        bag.mkdir()
    elif kind == 'corrupt metadata':
        bag.mkdir()
        (bag / 'metadata.yaml').write_text('rosbag2_bagfile_information: [not, a, bag')
    elif kind == 'corrupt mcap':
        write_commands(bag, range(10))
        mcap = bag / 'bag.mcap'
        mcap.write_bytes(mcap.read_bytes()[:-40])
    elif kind == 'no commands':
        with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            writer.add_connection(STATES_TOPIC, 'exit_decision_msgs/msg/VehicleStateArray', typestore=typestore())
    return bag


@pytest.mark.parametrize('kind, expected', [
    ('missing', 'no such bag; allowed: a rosbag2 (mcap) directory'),
    ('empty directory', 'empty directory, not a bag; allowed'),
    ('corrupt metadata', 'not a readable bag ('),
    ('corrupt mcap', 'not a readable bag ('),
    ('no commands', 'no recorded commands (/exit_decision/cav_commands); allowed: a bag the stack recorded'),
])
def test_replay_of_a_bad_bag_gives_one_line_and_a_non_zero_exit(tmp_path, capsys, kind, expected):
    bag = bad_bag(tmp_path, kind)
    assert main(['replay', str(bag)]) != 0
    err = capsys.readouterr().err
    assert expected in err and str(bag) in err and len(err.strip().splitlines()) == 1, err


def test_repair_refuses_what_is_no_unfinished_bag(tmp_path, capsys):
    assert main(['bag', 'repair', str(tmp_path / 'none')]) == 2
    assert 'no such bag directory' in capsys.readouterr().err
    write_commands(tmp_path / 'done', [0, 5])
    assert main(['bag', 'repair', str(tmp_path / 'done')]) == 2
    assert 'finished' in capsys.readouterr().err
