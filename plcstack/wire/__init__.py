"""See the wire: pcapng captures of the PLC traffic, the flight recorder, Wireshark
dissectors and the replay of a capture."""
