"""Fleet security: certificates, access control and per-host Zenoh configs (issue 15)."""
