"""The fleet: several daemons of one lab, joined through a NATS server with JetStream.

Each daemon (a node) owns the benches wired to its PC and leases their names in a JetStream
key-value bucket while it lives; it publishes its benches' readings to a JetStream stream and
answers the bench commands other nodes carry to it by request/reply. Every node lists the whole
fleet, streams any bench's readings and passes any bench's commands on to its owner. The one
store is the lab's PostgreSQL database, which every node reads and writes directly.
"""

from service.fleet.node import Fleet, FleetConflict, RemoteBench

__all__ = ["Fleet", "FleetConflict", "RemoteBench"]
