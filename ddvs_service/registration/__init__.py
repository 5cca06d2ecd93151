"""Direct image registration: planar (SL(3) + illumination, `planar`, `tracker`) and global initialisation."""
