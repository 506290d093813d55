"""The supervision protocol: what an operator's command asks a computer's supervisor (a
foreground ``msctl up`` or a robot's ``msctl agent``) and what it answers.

- :mod:`.contract`: the service's name and type, host namespaces, the bounds on a request
  (light: the quick path of ``msctl ps`` imports it).
- :mod:`.wire`: the request and answer as rmw_zenoh carries them, and the one client.
- :mod:`.protocol`: a typed struct per request (a tagged union by verb) and per answer.
- :mod:`.dispatch`: a table from verb to handler, and the answer to a pending request.

The runtime's own modules (the data monitor, the joint manager's presence feed) import these,
never the operator CLI.
"""
