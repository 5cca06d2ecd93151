#!/usr/bin/env bash
# Development PKI for ddvs Zenoh TLS / mutual TLS (docs/security.md).
#
# Usage: scripts/make_dev_certs.sh DIR
#
# Creates in DIR (idempotent: existing files are kept, missing ones are made):
#   ca.pem, ca.key                 a development certificate authority (10 years)
#   <role>.pem, <role>.key         one certificate per role, signed by the CA, Common Name = the role name,
#                                  SANs DNS:localhost and IP:127.0.0.1, usable as TLS server and client
# Roles: router service plant bridge operator observer (override with DDVS_CERT_ROLES="a b ...").
# Keys are ECDSA P-256 in PKCS#8 PEM. Development only: the CA key sits next to the certificates.
# DIR gets a .gitignore of '*' so that no key is committed by accident.
set -euo pipefail

if [[ $# -ne 1 || -z "$1" ]]; then
    echo "usage: $0 DIR   (directory for the development CA and the per-role certificates)" >&2
    exit 2
fi
command -v openssl >/dev/null || { echo "$0: openssl not found; install it (apt-get install openssl)" >&2; exit 1; }

dir=$1
roles=${DDVS_CERT_ROLES:-"router service plant bridge operator observer"}
days=3650
mkdir -p "$dir"
[[ -e "$dir/.gitignore" ]] || echo '*' >"$dir/.gitignore"  # private keys never go into git
umask 077
ext=$(mktemp)
trap 'rm -f "$ext"' EXIT
cat >"$ext" <<EXT
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=DNS:localhost,IP:127.0.0.1
EXT

new_key() {  # new_key PATH
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

if [[ ! -s "$dir/ca.pem" || ! -s "$dir/ca.key" ]]; then
    new_key "$dir/ca.key"
    openssl req -x509 -new -key "$dir/ca.key" -sha256 -days "$days" -subj "/CN=ddvs development CA" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -out "$dir/ca.pem"
    rm -f "$dir"/*.csr
    for role in $roles; do rm -f "$dir/$role.pem"; done  # certificates of a previous CA would no longer verify
    echo "created $dir/ca.pem"
fi

for role in $roles; do
    if [[ ! "$role" =~ ^[A-Za-z0-9_-]+$ ]]; then
        echo "$0: role '$role': expected letters, digits, '_' or '-'" >&2
        exit 2
    fi
    [[ -s "$dir/$role.pem" && -s "$dir/$role.key" ]] && continue
    new_key "$dir/$role.key"
    openssl req -new -key "$dir/$role.key" -subj "/CN=$role" -out "$dir/$role.csr"
    openssl x509 -req -in "$dir/$role.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" -CAcreateserial -sha256 \
        -days "$days" -extfile "$ext" -out "$dir/$role.pem" 2>/dev/null
    rm -f "$dir/$role.csr"
    openssl verify -CAfile "$dir/ca.pem" "$dir/$role.pem" >/dev/null
    echo "created $dir/$role.pem (CN=$role)"
done
chmod 644 "$dir"/*.pem
