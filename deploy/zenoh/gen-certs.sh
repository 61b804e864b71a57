#!/usr/bin/env bash
# Development certificates for the secured Zenoh router (docker-compose.secure.yml):
# a throw-away CA and a router certificate for the names clients dial (router, localhost,
# 127.0.0.1 and any extra names given), signed by that CA.
#
#   deploy/zenoh/gen-certs.sh [OUT_DIR] [EXTRA_DNS_NAME_OR_IP ...]
#
# OUT_DIR defaults to deploy/zenoh/certs (git-ignored). Writes ca.pem (give this to every
# client: transport/link/tls/root_ca_certificate), ca-key.pem (keep it; only needed to sign
# more certificates), router.pem and router-key.pem (the router's certificate and key).
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

openssl req -newkey rsa:2048 -nodes -sha256 -keyout router-key.pem -out router.csr \
  -subj "/CN=router" 2>/dev/null

ext="$(mktemp)"
trap 'rm -f "$ext" router.csr ca.srl' EXIT
cat > "$ext" <<EXT
basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth
subjectAltName=$san
EXT
openssl x509 -req -in router.csr -CA ca.pem -CAkey ca-key.pem -CAcreateserial -sha256 -days "$days" \
  -extfile "$ext" -out router.pem 2>/dev/null

# the CA and router certificates are public; the keys stay private (and out of git)
chmod 644 ca.pem router.pem
chmod 600 router-key.pem ca-key.pem
echo "wrote $out/{ca.pem,ca-key.pem,router.pem,router-key.pem} (router SAN: $san)"
