"""Damage injected into real point clouds: proxies of real buildings, damaged by the add-on, re-cast along the cloud's own pulses."""
