#!/bin/sh
# Creates the broker's users with random passwords, once (first start of the compose stack):
#   labeler     the service: reads unlabeled, publishes labeled/model/status
#   replay      capture sources: publish unlabeled only
#   subscriber  clients: read labeled/model/status only
# (permissions: docker/mosquitto.acl). Writes into DIR (default docker/secrets, git-ignored):
#   passwd            mosquitto password file (hashed)
#   <user>.password   the plain password of each user (mode 600), for the clients
#   labeler.env       MOCAP_MQTT__USERNAME / MOCAP_MQTT__PASSWORD for the service
#   replay.env, subscriber.env   MQTT_PASSWORD=... for those containers (compose env_file,
#                     read by docker compose itself, so every file stays mode 600)
# An existing DIR/passwd is kept (re-run with --force to replace every password).
# Needs mosquitto_passwd (apt install mosquitto) or docker (runs it in eclipse-mosquitto:2).
set -eu

force=0
if [ "${1:-}" = "--force" ]; then force=1; shift; fi
here=$(CDPATH= cd -- "$(dirname -- "$0")" && pwd)
dir=${1:-"$here/../docker/secrets"}
users="labeler replay subscriber"

umask 077
mkdir -p "$dir"
if [ -s "$dir/passwd" ] && [ "$force" -eq 0 ]; then
    echo "broker users exist in $dir (use --force to replace them)"
    exit 0
fi

if command -v mosquitto_passwd >/dev/null 2>&1; then
    hash_pw() { mosquitto_passwd -b "$dir/passwd" "$1" "$2"; }
elif command -v docker >/dev/null 2>&1; then
    abs=$(CDPATH= cd -- "$dir" && pwd)
    hash_pw() {
        docker run --rm -v "$abs:/s" eclipse-mosquitto:2 mosquitto_passwd -b /s/passwd "$1" "$2"
    }
else
    echo "error: need mosquitto_passwd (apt install mosquitto) or docker" >&2
    exit 2
fi

: > "$dir/passwd"
for user in $users; do
    pw=$(head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n')
    printf '%s' "$pw" > "$dir/$user.password"
    hash_pw "$user" "$pw"
done
printf 'MOCAP_MQTT__USERNAME=labeler\nMOCAP_MQTT__PASSWORD=%s\n' \
    "$(cat "$dir/labeler.password")" > "$dir/labeler.env"
for user in replay subscriber; do
    printf 'MQTT_PASSWORD=%s\n' "$(cat "$dir/$user.password")" > "$dir/$user.env"
done
# the broker container runs as user mosquitto (uid 1883): it must read the hashed file (the
# directory lets others reach a file they know the name of, not list it)
chmod 711 "$dir"
chmod 644 "$dir/passwd"
echo "broker users created in $dir: $users"
