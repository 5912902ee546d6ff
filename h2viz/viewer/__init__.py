"""The live dashboard: viser server, scene layers, novel-view renders and GUI panels (no torch)."""
