#!/usr/bin/env bash
# Development PKI for ddvs Zenoh TLS / mutual TLS (docs/security.md): `make certs [CERTS_DIR=certs]`.
#
# Usage: scripts/make_dev_certs.sh DIR [--robot NAME] [--prefix PREFIX] [--router-name HOST ...]
#
# Issues, idempotently, for robot PREFIX/NAME (default ddvs/robot0, that of configs/security; a fleet: its process
# name) (ddvs_service/protocol/pki.py; `ddvs security init` also writes every configuration):
#   DIR/ca/ca.pem, ca.key                     the robot's own certificate authority, CN "ddvs CA for ddvs/robot0"
#                                             (a DIR holding another robot's CA is refused)
#   DIR/router/{ca.pem,router.pem,router.key} the router: serverAuth only, CN router@ddvs/robot0, names localhost and
#                                             127.0.0.1 (or each --router-name)
#   DIR/<role>/{ca.pem,<role>.pem,<role>.key} each role: clientAuth only, CN <role>@ddvs/robot0, no names
# Roles: service plant bridge operator observer, or DDVS_CERT_ROLES="a b ..." (names: letters, digits, '_', '-').
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
python=${PYTHON:-$root/.venv/bin/python}
[[ -x "$python" ]] || python=python3
if [[ $# -lt 1 || -z "$1" ]]; then
    echo "usage: $0 DIR [--robot NAME] [--prefix PREFIX] [--router-name HOST ...]   (directory for the CA, the router's and each role's certificate)" >&2
    exit 2
fi
PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}" exec "$python" -m ddvs_service.protocol.pki "$@"
