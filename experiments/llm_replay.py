"""An OpenAI-compatible chat server on the loopback that answers from recorded answers, so that stage 2 runs
the litellm agent's whole path (prompts, litellm's HTTP call, parsing, program checks, the sandbox) without a
model, a key or a network; issue 38 trains the recorded programs against the offline planner's with it.

    python experiments/llm_replay.py --port 8765 -- .venv/bin/iarcs train --config CONFIG  # serves while it runs
    python experiments/llm_replay.py --port 8765                                           # until Ctrl-C

with a task block ``model: openai/recorded`` and ``api_base: http://127.0.0.1:8765/v1`` in CONFIG
(experiments/ablations/task_*_llm.yaml). A recorded answer is a JSON file ``TASK.json`` holding ``{"task",
"constraint", "response"}`` with ``"response"`` an OpenAI chat completion (``tests/fixtures/llm/*.json``: written by hand in the agent's
answer format, not by a model). The answer to a request is the one whose constraint the request quotes
(``Constraint: "..."``): to a synthesis request its program; to a reflection request (it holds "Training
feedback:") the recorded reflection answer for that constraint when there is one (``"reflection": true``), else
the same program again, i.e. the model keeps its program. Every request and the answer file it got are appended
to ``--log`` (JSON lines).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

RECORDED = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "llm"
CONSTRAINT = re.compile(r'Constraint: "(.*)"')


def load_answers(folder: Path) -> dict[tuple[str, bool], dict]:
    """``(constraint, is_reflection) -> recorded answer``: a task's answer is the file named after its task
    (``two_nightstands.json``), a reflection answer one marked ``"reflection": true``; the other files (the tests'
    failure behaviours: ``wrong_shape.json``, ...) are not answers."""
    answers = {}
    for path in sorted(Path(folder).glob("*.json")):
        entry = json.loads(path.read_text())
        if "response" in entry and (entry.get("task") == path.stem or entry.get("reflection")):
            answers[(entry["constraint"], bool(entry.get("reflection")))] = {**entry, "file": path.name}
    if not answers:
        raise SystemExit(f"llm_replay: no recorded answers in {folder} (TASK.json files with 'task', 'constraint' and "
                         "'response')")
    return answers


def choose(answers: dict, messages: list[dict]) -> tuple[dict | None, str]:
    """The recorded answer for a chat request, and a line saying why (or why none fits)."""
    text = "\n".join(m["content"] if isinstance(m["content"], str) else
                     "\n".join(p.get("text", "") for p in m["content"]) for m in messages if m["role"] == "user")
    found = CONSTRAINT.search(text)
    if not found:
        return None, "the request quotes no constraint (no line 'Constraint: \"...\"')"
    constraint, reflecting = found.group(1), "Training feedback:" in text
    entry = answers.get((constraint, reflecting)) or answers.get((constraint, False))
    if entry is None:
        known = "; ".join(sorted({c for c, _ in answers}))
        return None, f"no recorded answer for the constraint {constraint!r} (recorded: {known})"
    return entry, ("reflection" if reflecting else "synthesis")


class ReplayServer:
    """``POST /v1/chat/completions`` answered by :meth:`answer` (from ``answers``; 404 with the reason when none
    fits). The tests' scripted server (tests/test_llm_agent.py) overrides :meth:`answer`."""

    def __init__(self, answers: dict, port: int = 0, log: Path | None = None):
        self.answers, self.log = answers, log
        self.served: list[dict] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers.get("Content-Length", 0))))
                status, payload = server.answer(body, self.headers)
                data = json.dumps(payload).encode()
                try:
                    self.send_response(status)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                except OSError:  # the client gave up (its timeout)
                    pass

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
        self._thread.start()

    def answer(self, body: dict, headers) -> tuple[int, dict]:
        """(HTTP status, JSON payload) for one chat request."""
        entry, why = choose(self.answers, body.get("messages", []))
        record = {"kind": why if entry else "refused", "file": entry["file"] if entry else None}
        if entry is None:
            record["reason"] = why
        self.served.append(record)
        if self.log:
            with open(self.log, "a") as f:
                f.write(json.dumps(record) + "\n")
        if entry is None:
            return 404, {"error": {"message": f"llm_replay: {why}", "type": "invalid_request_error", "code": 404}}
        return 200, {**entry["response"], "model": body.get("model", "recorded")}

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--port", type=int, default=8765, help="loopback port (the config's api_base names it)")
    parser.add_argument("--answers", type=Path, default=RECORDED, help=f"folder of recorded answers ({RECORDED})")
    parser.add_argument("--log", type=Path, help="append each request's answer file here (JSON lines)")
    args = parser.parse_args(own)
    try:
        server = ReplayServer(load_answers(args.answers), args.port, args.log)
    except OSError as err:
        raise SystemExit(f"llm_replay: cannot listen on 127.0.0.1:{args.port} ({err.strerror}); pick another --port "
                         "and the same port in the config's api_base") from None
    print(f"llm_replay: answering at {server.url} from {args.answers}", file=sys.stderr, flush=True)
    try:
        if command:
            return subprocess.call(command)
        server._thread.join()
        return 0
    except KeyboardInterrupt:
        return 130
    finally:
        server.close()


if __name__ == "__main__":
    sys.exit(main())
