#!/usr/bin/env bash
# Development certificates for the secured Zenoh router (docker-compose.secure.yml):
# a throw-away CA and two router certificates for the names clients dial (router, localhost,
# 127.0.0.1 and any extra names given), signed by that CA:
#   * router.pem (common name zenrl-central-router): the central router's;
#   * host-router.pem (common name zenrl-host-router): the host routers' (host-router-secure.json5).
# A host router trusts the link to the central router by that link's verified certificate (its
# common name zenrl-central-router, signed by ca.pem), so only the central router's key may be
# on the central router's machine: a host router holds host-router-key.pem, never router-key.pem.
#
#   deploy/zenoh/gen-certs.sh [OUT_DIR] [EXTRA_DNS_NAME_OR_IP ...]
#
# OUT_DIR defaults to deploy/zenoh/certs (git-ignored). Writes ca.pem (give this to every
# client: transport/link/tls/root_ca_certificate), ca-key.pem (keep it; only needed to sign
# more certificates), router.pem and router-key.pem (the central router's certificate and key),
# host-router.pem and host-router-key.pem (the host routers').
# Not for production: use your own CA there. Existing files are overwritten.
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
out="${1:-$here/certs}"
shift || true
days="${CERT_DAYS:-825}"

mkdir -p "$out"
cd "$out"

san="DNS:router,DNS:localhost,IP:127.0.0.1,IP:::1"
for name in "$@"; do
  if [[ "$name" =~ ^[0-9.]+$ || "$name" == *:* ]]; then san="$san,IP:$name"; else san="$san,DNS:$name"; fi
done

openssl req -x509 -newkey rsa:2048 -nodes -sha256 -days "$days" \
  -keyout ca-key.pem -out ca.pem -subj "/CN=zenrl development CA" \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null

ext="$(mktemp)"
trap 'rm -f "$ext" router.csr ca.srl' EXIT
cat > "$ext" <<EXT
basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth
subjectAltName=$san
EXT

# issue NAME COMMON_NAME: NAME.pem and NAME-key.pem, signed by the CA
issue() {
  openssl req -newkey rsa:2048 -nodes -sha256 -keyout "$1-key.pem" -out router.csr -subj "/CN=$2" 2>/dev/null
  openssl x509 -req -in router.csr -CA ca.pem -CAkey ca-key.pem -CAcreateserial -sha256 -days "$days" \
    -extfile "$ext" -out "$1.pem" 2>/dev/null
}
issue router zenrl-central-router
issue host-router zenrl-host-router

# the CA and router certificates are public; the keys stay private (and out of git)
chmod 644 ca.pem router.pem host-router.pem
chmod 600 router-key.pem host-router-key.pem ca-key.pem
echo "wrote $out/{ca.pem,ca-key.pem,router.pem,router-key.pem,host-router.pem,host-router-key.pem} (router SAN: $san)"
