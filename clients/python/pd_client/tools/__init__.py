"""The command-line tools of pd-client, one module per command.

=====================  ===========================================================
``pd_robot_sim``       ``pd-robot-sim``: a simulated robot running a scenario in real time
``pd_operator``        ``pd-operator``: a scripted operator sending a scenario's commands
``pd_display``         ``pd-display``: a live terminal view of one session's predictions
``pd_record``          ``pd-record``: predictions and truth to CSV, summary, PNG plots
``pd_demo``            ``pd-demo``: the whole system on one machine, then a summary
``record_csv``         the pd-record CSV format: reading it back and summarising it
``plots``              PNG plots of pd-record CSVs (needs matplotlib: the ``plots`` extra)
``common``             what every tool shares: its main, the Zenoh flags, logging, the clock
=====================  ===========================================================

``python -m pd_client.tools sim|operator|display|record`` runs them without installed scripts.
The SDK (``import pd_client``) imports none of these.
"""
