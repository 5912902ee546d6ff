"""Tests of the live dashboard (viser server, layers, panels, headless browser)."""
