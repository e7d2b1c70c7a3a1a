#!/usr/bin/env python3
"""How long a respawned breast_sim node takes to be ready again after SIGKILL.

Runs against a node started by launch/breast_sim.launch (respawn="true"): waits until the node is
precomputed (its checkpoint is written then), kills it with SIGKILL --kills times, and measures for
each restart, until ~state says the checkpoint was resumed (the node tracks the next cloud from there):
the time from the kill, and from the launch of the respawned process (its start time in /proc).
Prints a table; --json FILE writes the same figures.

  roslaunch breast_sim breast_sim.launch target_elements:=20000 precompute_on_start:=true \\
      state_folder:=/tmp/restart_states &
  /usr/bin/python3 scripts/measure_restart.py --kills 3 [--json restart.json]

Debian's python3 (rospy); the node must run on the same machine (its process is killed). ~state is
read as raw bytes (breast_sim/NodeState, decoded below): the generated Python messages of the package
import geometry_msgs, which Debian does not ship for Python.
"""
import argparse
import json
import os
import signal
import struct
import sys
import threading
import time
import xmlrpc.client

import rosgraph
import rospy

IDLE = 0  # breast_sim/NodeState.IDLE


class NodeState:
    """The fields of breast_sim/NodeState this script reads, from the serialized message."""

    def __init__(self, data):
        pos = 12  # header: seq, stamp (secs, nsecs)

        def string():
            nonlocal pos
            (n,) = struct.unpack_from('<I', data, pos)
            pos += 4 + n
            return data[pos - n:pos].decode('utf-8', 'replace')

        string()  # header.frame_id
        self.state = data[pos]
        pos += 1
        self.state_name = string()
        self.stage = string()
        pos += 8 + 4 + 4  # progress, step, max_steps
        self.model_loaded, self.precomputed = bool(data[pos]), bool(data[pos + 1])
        pos += 2
        self.case_name = string()
        self.message = string()


class States:
    def __init__(self):
        self.lock = threading.Lock()
        self.messages = []  # (monotonic time, NodeState)

    def __call__(self, raw):
        msg = NodeState(raw._buff)
        with self.lock:
            self.messages.append((time.monotonic(), msg))

    def wait(self, condition, timeout_s, since=0.0):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not rospy.is_shutdown():
            with self.lock:
                for t, m in self.messages:
                    if t >= since and condition(m):
                        return t, m
            time.sleep(0.01)
        return None, None


def node_pid(name):
    """The node's process id from its own XML-RPC API, or None while it does not answer."""
    try:
        uri = rosgraph.Master('/measure_restart').lookupNode(name)
        code, _, pid = xmlrpc.client.ServerProxy(uri).getPid('/measure_restart')
        return pid if code == 1 else None
    except Exception:
        return None


def process_age_s(pid):
    with open('/proc/%d/stat' % pid) as f:
        fields = f.read().rsplit(')', 1)[1].split()
    start_ticks = int(fields[19])  # field 22 of stat; the split starts at field 3
    with open('/proc/uptime') as f:
        uptime_s = float(f.read().split()[0])
    return uptime_s - start_ticks / os.sysconf('SC_CLK_TCK')


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--node', default='/breast_sim')
    parser.add_argument('--kills', type=int, default=3)
    parser.add_argument('--timeout', type=float, default=1800.0, help='wait for the precomputation [s]')
    parser.add_argument('--json', help='write the figures to this file')
    args = parser.parse_args(rospy.myargv()[1:])
    rospy.init_node('measure_restart', anonymous=False, disable_signals=True)
    states = States()
    rospy.Subscriber(args.node + '/state', rospy.AnyMsg, states, queue_size=100)
    t, m = states.wait(lambda m: m.precomputed and m.state == IDLE, args.timeout)
    if m is None:
        sys.exit('the node was not precomputed within %.0f s' % args.timeout)
    case = m.case_name
    rows = []
    for k in range(args.kills):
        pid = node_pid(args.node)
        if pid is None:
            sys.exit('the node does not answer getPid')
        time.sleep(1.0)
        t_kill = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        new_pid = None
        while time.monotonic() - t_kill < 60 and (new_pid is None or new_pid == pid):
            new_pid = node_pid(args.node)
            time.sleep(0.02)
        t_ready, msg = states.wait(lambda m: 'resumed case' in m.message, 600.0, since=t_kill)
        if msg is None:
            sys.exit('restart %d: the respawned node did not resume a checkpoint' % (k + 1))
        launch_to_ready = process_age_s(new_pid) - (time.monotonic() - t_ready)
        rows.append({'restart': k + 1, 'kill_to_ready_s': round(t_ready - t_kill, 3),
                     'launch_to_ready_s': round(launch_to_ready, 3)})
    with open('/proc/loadavg') as f:
        load = float(f.read().split()[0])
    print('case %s; ready = ~state says the checkpoint was resumed (the next cloud is tracked); load %.1f' % (case, load))
    print('%8s  %14s  %16s' % ('restart', 'kill->ready s', 'launch->ready s'))
    for r in rows:
        print('%8d  %14.2f  %16.2f' % (r['restart'], r['kill_to_ready_s'], r['launch_to_ready_s']))
    if args.json:
        with open(args.json, 'w') as f:
            json.dump({'case': case, 'load_average': load, 'restarts': rows}, f, indent=1)
    rospy.signal_shutdown('done')


if __name__ == '__main__':
    main()
