"""Deployment: a team's certificates, its fleet description and each node's Zenoh configuration.

`pki` makes the team's certificate authority and one key + certificate per node (and one for the
operator); `fleet` reads the fleet file that maps the scenario's nodes to host addresses;
`zenoh_config` turns both into each node's Zenoh settings (mutual TLS on every link, scouting
off, fixed endpoints along the scenario's links, the lease, default-deny access control) and
`units` writes the files a robot needs (json5 configuration, systemd unit).

May import: errors, model, protocol, runtime (the layers below). Used by launch and cli.
"""
