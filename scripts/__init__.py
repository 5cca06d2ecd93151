"""Project scripts: the set-up (setup.sh), development certificates and the documentation generators (docsgen)."""
