"""The one training loop every playseg model trains through (loop.py), and the device it runs on
(device.py)."""
