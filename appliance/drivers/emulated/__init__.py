"""Register-level emulators of the front end's chips behind fake buses, and the analogue chain behind them."""
