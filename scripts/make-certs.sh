#!/usr/bin/env bash
# A throw-away certificate authority and certificates for hilsim over TLS (docs/security.md).
#
#   scripts/make-certs.sh [DIR] [--host NAME_OR_IP]...   (DIR default: config/security/certs)
#
# Writes DIR/ca.pem (+ ca.key), DIR/router.pem + router.key (the router's server certificate,
# valid for localhost, 127.0.0.1 and every --host), and a client certificate + key per identity
# whose common name config/security/router.json5 knows: workstation, robot, bridge (services),
# recorder (services that may not actuate), operator (goals and gains), observer (read only).
# EC P-256 keys, 30 days. For trials only: a real deployment keeps its CA key off the robots.
set -euo pipefail
DIR=config/security/certs
HOSTS=()
while [ $# -gt 0 ]; do
  case "$1" in
    --host) HOSTS+=("$2"); shift 2 ;;
    -h|--help) sed -n '2,11p' "$0"; exit 0 ;;
    -*) echo "make-certs.sh: unknown option $1" >&2; exit 2 ;;
    *) DIR="$1"; shift ;;
  esac
done
command -v openssl >/dev/null || { echo "make-certs.sh: openssl is not installed" >&2; exit 2; }
mkdir -p "$DIR"
cd "$DIR"
DAYS=30
key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; chmod 600 "$1"; }

key ca.key
openssl req -x509 -new -key ca.key -sha256 -days "$DAYS" -subj "/CN=hilsim throw-away CA" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" -out ca.pem

# sign NAME EXT: a certificate for common name NAME with the extensions in EXT
sign() {
  key "$1.key"
  openssl req -new -key "$1.key" -subj "/CN=$1" -out "$1.csr"
  printf '%s\n' "$2" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days "$DAYS" -sha256 \
    -extfile "$1.ext" -out "$1.pem" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
}

SAN="DNS:localhost,IP:127.0.0.1"
for h in "${HOSTS[@]+"${HOSTS[@]}"}"; do
  if [[ "$h" =~ ^[0-9.]+$ || "$h" == *:* ]]; then SAN="$SAN,IP:$h"; else SAN="$SAN,DNS:$h"; fi
done
sign router "basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth
subjectAltName=$SAN"
for who in workstation robot bridge recorder operator observer; do
  sign "$who" "basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth"
done
rm -f ca.srl
echo "certificates in $(pwd): ca.pem, router.pem, and workstation robot bridge recorder operator observer (.pem + .key)"
