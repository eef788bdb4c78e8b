"""Real laser-line turntable scans: reader, markers, pose graph, laser points, mesh, report."""
