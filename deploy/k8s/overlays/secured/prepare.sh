#!/usr/bin/env bash
# Makes deploy/k8s/components/secured/files/ for the secured overlays (overlays/secured,
# overlays/league-secured): the inputs of the component's secretGenerator and configMapGenerator.
#
#   deploy/k8s/overlays/secured/prepare.sh [NAMESPACE] [ACTORS]
#
# * certificates (deploy/zenoh/gen-certs.sh): a development CA and a router certificate naming
#   the router Service (zenrl-router, zenrl-router.NAMESPACE.svc[.cluster.local]); skipped when
#   files/ca.pem exists, so you can put your own CA, router.pem and router-key.pem there instead;
# * fresh credentials (`zenrl credentials`, so zenrl must be installed: pip install -e .): random
#   passwords in users.txt, client-<role>.json5, actor-logins.json (actor-0 .. actor-<ACTORS-1>,
#   default 16: at most that many actor pods), and router-secure.json5 with the access control
#   for those actors; kept when files/users.txt exists (delete it, or files/, for a new set).
#
# files/ is git-ignored; kustomize turns it into Secrets when the overlay is applied, so no
# secret is ever part of a manifest in the repository.
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
zenoh="$(cd "$here/../../../zenoh" && pwd)"
ns="${1:-default}"
out="$(cd "$here/../../components/secured" && pwd)/files"
# files/ used to be made beside this script: a set made there is moved, not replaced (its
# passwords may be in use by a running cluster)
if [[ -d "$here/files" && ! -e "$out" ]]; then
  mv "$here/files" "$out"
fi
mkdir -p "$out"

if [[ ! -f "$out/ca.pem" ]]; then
  bash "$zenoh/gen-certs.sh" "$out" zenrl-router "zenrl-router.$ns.svc" "zenrl-router.$ns.svc.cluster.local" >/dev/null
fi
for f in router.pem router-key.pem; do
  [[ -f "$out/$f" ]] || { echo "prepare.sh: $out/$f is missing (a CA is there but no router certificate)" >&2; exit 1; }
done
python="${PYTHON:-python3}"  # the Python that has zenrl
"$python" -m zenrl.cli credentials --out "$out" --templates "$zenoh" --actors "${2:-16}" >/dev/null \
  || { echo "prepare.sh: zenrl credentials failed (is zenrl installed? pip install -e .)" >&2; exit 1; }
chmod 600 "$out"/*-key.pem
echo "wrote $out (namespace $ns, actor logins: $("$python" -c "import json,sys; print(len(json.load(open(sys.argv[1]))))" "$out/actor-logins.json"))"
