"""The hospital's history in PostgreSQL, fed from the engine: every alarm, turn and episode event once, and each
bed's pressure down-sampled to one row a minute, in time partitions that retention drops whole.

``schema`` holds the tables and their partitions, ``trend`` the down-sampling of the beds' summaries,
``writer`` the consumer from the engine, ``reads`` what the ward and hospital screens ask of it.
"""
