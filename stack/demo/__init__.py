"""`formation demo`: the main job in resumable stages (see :mod:`stack.commands.demo`).

Modules:
    state    settings, ``stages.json`` (which stages are done, atomic writes), child processes
             in their own process groups and the Ctrl-C handler that ends them
    stages   the stages: train-3, train-5 (transfer + zero-shot), export, fleet, generalist
             (train on 3-5 robots, zero-shot table, export)
    fleet    fleet-sim and bridge as separate processes over loopback Zenoh (fleet, fleet-unseen)
    report   metrics.json, report.md and report.html with the figures of :mod:`stack.plots`
"""
