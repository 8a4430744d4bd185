"""The simulator: synthetic captures, a world with a chair in it, and rendered camera frames."""
