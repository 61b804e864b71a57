#!/usr/bin/env bash
# Makes files/ for the secured overlay: the inputs of its secretGenerator and configMapGenerator.
#
#   deploy/k8s/overlays/secured/prepare.sh [NAMESPACE]
#
# * certificates (deploy/zenoh/gen-certs.sh): a development CA and a router certificate naming
#   the router Service (zenrl-router, zenrl-router.NAMESPACE.svc[.cluster.local]); skipped when
#   files/ca.pem exists, so you can put your own CA, router.pem and router-key.pem there instead;
# * router-secure.json5 (the access control), users.txt and client-<role>.json5 copied from
#   deploy/zenoh. These hold DEVELOPMENT passwords: change each one in files/users.txt and the
#   matching files/client-<role>.json5 (and hostrouter in users.txt) before the cluster is
#   reachable from anywhere untrusted.
#
# files/ is git-ignored; kustomize turns it into Secrets when the overlay is applied, so no
# secret is ever part of a manifest in the repository.
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
zenoh="$(cd "$here/../../../zenoh" && pwd)"
ns="${1:-default}"
out="$here/files"
mkdir -p "$out"

if [[ ! -f "$out/ca.pem" ]]; then
  bash "$zenoh/gen-certs.sh" "$out" zenrl-router "zenrl-router.$ns.svc" "zenrl-router.$ns.svc.cluster.local" >/dev/null
fi
for f in router.pem router-key.pem; do
  [[ -f "$out/$f" ]] || { echo "prepare.sh: $out/$f is missing (a CA is there but no router certificate)" >&2; exit 1; }
done
cp "$zenoh/router-secure.json5" "$zenoh/users.txt" "$out/"
for role in actor learner replay evaluator monitor; do
  cp "$zenoh/client-$role.json5" "$out/"
done
chmod 600 "$out"/*-key.pem "$out/users.txt" "$out"/client-*.json5
echo "wrote $out (namespace $ns); change the development passwords before real use"
