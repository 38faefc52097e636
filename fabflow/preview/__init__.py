"""The browser scene (viser), live and exported as one HTML file."""
