"""Device drivers: a transport plus a codec, usable on their own as context managers."""
