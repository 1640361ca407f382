"""Example configurations shipped with the package (``plcstack demo --write-config``)."""
