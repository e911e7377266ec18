"""Table II action conversion, the serial motor-controller protocol and link, the drive node and a simulated controller."""
