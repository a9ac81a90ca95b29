"""Does a quorum queue with single-active-consumer deliver in order to the next consumer after a hand-over?

A 3-node RabbitMQ cluster (roadgrip/cloud/transport/amqp.py `RabbitCluster`, the workers' test fixture), one partition
queue, a publisher of numbered messages (8 every 10 ms, through node 2) and three consumers (nodes 0, 1, 2; prefetch
500, as a worker's) that take turns as the worker's hand-over does: the active one acknowledges what it took,
stops taking, and closes its connection; the next waiting consumer becomes active. Each consumer's deliveries
are checked for order (a message number lower than the one before it):

    python results/trials/cluster/handover_order.py --hand-overs 18

Measured 2026-12-06 on RabbitMQ 3.10.8 (Debian 12), two runs: 15 and 13 of 19 turns began out of order, among the
returned messages themselves (10106-10111 before 10104) and between them and newer ones (5621-5623, new, before
5617-5620, redelivered; 6330-6335 before 6296), all in the first burst. roadgrip/cloud/pipeline/pipeline.py
`TAKEOVER_HOLD_S` is the worker's answer.
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path

import pika

from roadgrip.cloud.transport.amqp import RabbitCluster, partition_queue

QUEUE = partition_queue(0)


class Consumer:
    """A consumer on `node` that holds the queue until `release` is set, then closes and registers again."""

    def __init__(self, rabbit: RabbitCluster, node: int, stop: threading.Event):
        self.rabbit, self.node, self.stop = rabbit, node, stop
        self.turns: list[list[tuple[int, bool]]] = []  # per turn as the active consumer: (message, redelivered)
        self.release = threading.Event()
        self.ready = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while not self.stop.is_set():
            connection = pika.BlockingConnection(pika.URLParameters(self.rabbit.amqp_url(self.node)))
            channel = connection.channel()
            channel.basic_qos(prefetch_count=500)
            taken: list[tuple[int, int, bool]] = []
            taking = [True]

            def on_message(channel, method, properties, body, taken=taken, taking=taking):
                if taking[0]:  # after the release: left unacknowledged, returned at the close
                    taken.append((method.delivery_tag, int(body), method.redelivered))

            channel.basic_consume(QUEUE, on_message)
            self.ready.set()
            acknowledged = 0
            while not self.stop.is_set():
                connection.process_data_events(time_limit=0)
                if taken and taken[-1][0] > acknowledged:
                    acknowledged = taken[-1][0]
                    channel.basic_ack(acknowledged, multiple=True)
                if self.release.is_set():
                    taking[0] = False
                    connection.process_data_events(time_limit=0.2)
                    break
                time.sleep(0.05)
            self.release.clear()
            connection.close()
            if taken:
                self.turns.append([(n, redelivered) for _, n, redelivered in taken])


def publish(rabbit: RabbitCluster, stop: threading.Event) -> None:
    connection = pika.BlockingConnection(pika.URLParameters(rabbit.amqp_url(2)))
    channel = connection.channel()
    n = 0
    while not stop.is_set():
        for _ in range(8):
            channel.basic_publish("", QUEUE, str(n).encode())
            n += 1
        connection.process_data_events(time_limit=0)
        time.sleep(0.01)
    connection.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hand-overs", type=int, default=18)
    args = parser.parse_args()
    rabbit = RabbitCluster(Path(tempfile.mkdtemp(prefix="handover-order-")), ["v00"], 4, "handover-order")
    stop = threading.Event()
    try:
        rabbit.start()
        rabbit.setup()
        threading.Thread(target=publish, args=(rabbit, stop), daemon=True).start()
        consumers = []
        for node in range(3):
            consumers.append(Consumer(rabbit, node, stop))
            consumers[-1].ready.wait()
            time.sleep(0.5)
        for k in range(args.hand_overs):
            consumers[k % 3].release.set()
            time.sleep(1.0)
        stop.set()
        time.sleep(1.0)
    finally:
        rabbit.stop()
    turns = [turn for c in consumers for turn in c.turns]
    disordered = 0
    for turn in turns:
        numbers = [n for n, _ in turn]
        first = next((i for i in range(1, len(numbers)) if numbers[i] < numbers[i - 1]), None)
        if first is not None:
            disordered += 1
            around = turn[max(0, first - 6) : first + 4]
            print("out of order:", " ".join(f"{n}{'r' if r else ''}" for n, r in around), "(r: redelivered)")
    print(f"{disordered} of {len(turns)} turns as the active consumer began out of order")


if __name__ == "__main__":
    main()
