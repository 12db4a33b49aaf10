"""Tele-Touch cloud relay: sessions, auth, per-stream forwarding and latency accounting."""
