"""Point detection (Shi-Tomasi) and the trackability test on the structure tensor."""
