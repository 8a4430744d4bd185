"""Device drivers behind small interfaces; each has an emulator backend chosen by configuration."""
