"""The LLM backend of the reward agent: one chat-completion call through litellm, with a disk cache,
retries with exponential backoff, running token/cost totals and errors that say what to fix.

    client = LLMClient(LLMConfig(model="gemini/gemini-2.5-pro", cache_dir="runs/llm_cache"))
    reply = client.complete([{"role": "user", "content": "..."}])
    reply.text, reply.cost, client.usage.to_dict()

Any provider litellm knows works: ``gemini/gemini-2.5-pro`` (the paper's, key in ``GEMINI_API_KEY``),
``openai/<name>`` with ``api_base`` for an OpenAI-compatible server (vLLM, llama.cpp), ``ollama/<name>``.
litellm (pinned to 1.106.2) is imported on first use only: the import takes 3-4 s.

Retries: rate limits (429), server errors (5xx, connection refused) and timeouts are retried with
exponential backoff (``backoff_base * 2**k`` seconds, at most ``backoff_max``); authentication and bad
requests are not. litellm's own ``num_retries`` is not used (it needs tenacity).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import re
import tempfile
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

_litellm = None


def load_litellm():
    """litellm, imported once (3-4 s) with the bundled model cost map (no network at import)."""
    global _litellm
    if _litellm is None:
        os.environ.setdefault("LITELLM_LOCAL_MODEL_COST_MAP", "True")
        import litellm

        litellm.suppress_debug_info = True  # no "Give Feedback / Get Help" banners on every error
        _litellm = litellm
    return _litellm


# ----------------------------------------------------------------------------------------------- errors


class LLMError(RuntimeError):
    """A model call that failed; the message says what was wrong and how to fix it."""

    retriable = False

    def __init__(self, message: str, attempts: int = 0):
        super().__init__(message)
        self.attempts = attempts


class LLMConfigError(LLMError):
    """The configuration cannot work (no API key, unknown provider); nothing was sent."""


class LLMAuthError(LLMError):
    """The server rejected the credentials (401/403)."""


class LLMBadRequestError(LLMError):
    """The server rejected the request (400/404/422: unknown model, prompt too long, bad parameter)."""


class LLMRateLimitError(LLMError):
    """Still rate limited (429) after all retries."""

    retriable = True


class LLMServerError(LLMError):
    """The server kept failing (5xx) after all retries."""

    retriable = True


class LLMConnectionError(LLMServerError):
    """The server could not be reached (connection refused, DNS failure) after all retries."""


class LLMTimeoutError(LLMError):
    """No answer within the timeout, on every attempt."""

    retriable = True


# ------------------------------------------------------------------------------------------ config/types


@dataclass
class LLMConfig:
    """How to reach the model. Build from YAML with :meth:`from_dict`."""

    model: str
    """litellm model name with provider prefix: ``gemini/gemini-2.5-pro``, ``openai/<name>``, ``ollama/<name>``."""
    api_base: str | None = None
    """Server URL for self-hosted models, e.g. ``http://localhost:8000/v1`` (vLLM) or ``http://localhost:11434``."""
    api_key: str | None = None
    """The key itself (prefer ``api_key_env`` so that keys stay out of config files)."""
    api_key_env: str | None = None
    """Name of the environment variable holding the key (default: the provider's, e.g. ``GEMINI_API_KEY``)."""
    timeout: float = 120.0
    """Seconds to wait for one answer."""
    max_seconds: float = 240.0
    """Longest one synthesis or reflection may take: every request, retry and back-off included."""
    max_retries: int = 4
    """Retries after the first try, for rate limits, server errors and timeouts."""
    backoff_base: float = 2.0
    """First retry delay in seconds; doubles on every retry."""
    backoff_max: float = 60.0
    """Longest retry delay in seconds."""
    temperature: float = 0.2
    max_tokens: int | None = 8192
    cache_dir: str | None = None
    """Folder of cached answers (one JSON file per prompt); None turns the cache off."""
    input_cost_per_token: float | None = None
    """USD per prompt token for models litellm has no price for (self-hosted ones cost 0 otherwise)."""
    output_cost_per_token: float | None = None
    """USD per completion token, as above."""
    extra: dict[str, Any] = field(default_factory=dict)
    """More keyword arguments for ``litellm.completion`` (e.g. ``reasoning_effort``)."""

    @classmethod
    def from_dict(cls, data: dict | str) -> "LLMConfig":
        """From a YAML mapping (or a bare model name); unknown keys are an error that lists the valid ones."""
        if isinstance(data, str):
            return cls(model=data)
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(f"unknown llm config key(s) {', '.join(unknown)}; valid keys: {', '.join(names)}")
        if not data.get("model"):
            raise ValueError("llm config needs a 'model', e.g. gemini/gemini-2.5-pro or openai/<name> with api_base")
        return cls(**data)

    def to_dict(self) -> dict:
        """As a plain dict, with the key itself hidden."""
        out = asdict(self)
        if out["api_key"]:
            out["api_key"] = "***"
        return out


@dataclass
class LLMReply:
    """One answer. A cached answer cost nothing now: its tokens and cost are 0."""

    text: str
    prompt_tokens: int
    completion_tokens: int
    cost: float
    """USD for this call (0 when cached or when the model's price is unknown)."""
    cached: bool
    model: str
    attempts: int = 1
    """HTTP attempts this answer took (1 + retries; 0 when cached)."""


@dataclass
class LLMUsage:
    """Running totals of one client."""

    calls: int = 0
    """Answers returned (cached ones included)."""
    cache_hits: int = 0
    requests: int = 0
    """HTTP requests sent (retries included)."""
    retries: int = 0
    backoff_seconds: float = 0.0
    """Time spent waiting between retries."""
    prompt_tokens: int = 0
    completion_tokens: int = 0
    cost: float = 0.0
    errors: int = 0
    """Calls that ended in an LLMError."""

    def to_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------------------------------------- client


class LLMClient:
    """Chat completions through litellm with cache, retries and usage totals."""

    def __init__(self, config: LLMConfig | dict | str | None = None, **kwargs):
        if config is None:
            config = LLMConfig(**kwargs)
        elif kwargs:
            raise TypeError("pass either a config or keyword arguments, not both")
        elif not isinstance(config, LLMConfig):
            config = LLMConfig.from_dict(config)
        self.config = config
        self.usage = LLMUsage()
        self._vision: bool | None = None

    @property
    def model(self) -> str:
        return self.config.model

    @property
    def supports_vision(self) -> bool:
        """Whether litellm knows this model to accept images (False for unknown models)."""
        if self._vision is None:
            try:
                self._vision = bool(load_litellm().supports_vision(self.config.model))
            except Exception:  # unknown model or provider
                self._vision = False
        return self._vision

    # -- cache

    def cache_key(self, messages: list[dict]) -> str:
        """sha256 of model, messages and temperature."""
        blob = json.dumps({"model": self.config.model, "messages": messages,
                           "temperature": self.config.temperature}, sort_keys=True, ensure_ascii=True)
        return hashlib.sha256(blob.encode()).hexdigest()

    def _cache_path(self, key: str) -> Path | None:
        return Path(self.config.cache_dir) / f"{key}.json" if self.config.cache_dir else None

    def _cache_get(self, key: str) -> dict | None:
        path = self._cache_path(key)
        if path is None or not path.exists():
            return None
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):  # a damaged entry is a miss
            return None

    def _cache_put(self, key: str, entry: dict) -> None:
        path = self._cache_path(key)
        if path is None:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".json")
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(entry, f, indent=1)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    # -- the call

    def complete(self, messages: list[dict], deadline: float | None = None) -> LLMReply:
        """The model's answer to a chat (OpenAI message format); cached answers are returned at no cost.
        ``deadline`` (``time.monotonic()``) bounds every request and retry.

        Raises an :class:`LLMError` subclass when no answer could be had."""
        key = self.cache_key(messages)
        hit = self._cache_get(key)
        if hit is not None and isinstance(hit.get("text"), str):
            self.usage.calls += 1
            self.usage.cache_hits += 1
            return LLMReply(hit["text"], 0, 0, 0.0, True, hit.get("model", self.config.model), attempts=0)
        try:
            reply = self._call_with_retries(messages, deadline)
        except LLMError:
            self.usage.errors += 1
            raise
        self.usage.calls += 1
        self.usage.prompt_tokens += reply.prompt_tokens
        self.usage.completion_tokens += reply.completion_tokens
        self.usage.cost += reply.cost
        if reply.text.strip():
            self._cache_put(key, {"model": reply.model, "text": reply.text, "prompt_tokens": reply.prompt_tokens,
                                  "completion_tokens": reply.completion_tokens, "cost": reply.cost,
                                  "created": time.time()})
        return reply

    def check(self) -> None:
        """Raise :class:`LLMConfigError` now if no API key can be found (sends nothing)."""
        self._api_key()

    def _request_kwargs(self, messages: list[dict]) -> dict:
        cfg = self.config
        kwargs: dict[str, Any] = dict(model=cfg.model, messages=messages, timeout=cfg.timeout,
                                      temperature=cfg.temperature, max_retries=0, drop_params=True)
        if cfg.max_tokens:
            kwargs["max_tokens"] = cfg.max_tokens
        if cfg.api_base:
            kwargs["api_base"] = cfg.api_base
        key = self._api_key()
        if key:
            kwargs["api_key"] = key
        kwargs.update(cfg.extra)
        return kwargs

    def _api_key(self) -> str | None:
        """The key to send; raises LLMConfigError (before any request) when a hosted provider has none."""
        cfg = self.config
        if cfg.api_key:
            return cfg.api_key
        if cfg.api_key_env:
            key = os.environ.get(cfg.api_key_env)
            if not key:
                raise LLMConfigError(f"no API key for {cfg.model}: the environment variable {cfg.api_key_env} "
                                     f"(named by api_key_env) is not set; export {cfg.api_key_env}=<your key>")
            return key
        try:
            env = load_litellm().validate_environment(cfg.model)
        except Exception:
            return None
        missing = [k for k in env.get("missing_keys", []) if k.endswith(("_KEY", "_TOKEN"))]
        if env.get("keys_in_environment") or not missing:
            return None
        if cfg.api_base:
            # a self-hosted OpenAI-compatible server usually ignores the key, but the client needs one
            return "EMPTY"
        names = " or ".join(missing)
        raise LLMConfigError(f"no API key for {cfg.model}: set the environment variable {names} "
                             f"(e.g. export {missing[-1]}=<your key>), or give api_key / api_key_env in the llm "
                             f"config; for a self-hosted OpenAI-compatible server use model openai/<name> "
                             f"with api_base")

    def _call_with_retries(self, messages: list[dict], deadline: float | None = None) -> LLMReply:
        litellm = load_litellm()
        kwargs = self._request_kwargs(messages)
        cfg = self.config
        attempt = 0
        while True:
            attempt += 1
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise self._out_of_time(attempt - 1)
                kwargs["timeout"] = min(cfg.timeout, left)
            self.usage.requests += 1
            try:
                response = litellm.completion(**kwargs)
            except Exception as exc:  # classified below; anything unknown is not retried
                error_cls = _classify(exc)
                if not error_cls.retriable or attempt > cfg.max_retries:
                    raise self._error(error_cls, exc, attempt) from exc
                delay = min(cfg.backoff_max, cfg.backoff_base * 2 ** (attempt - 1)) * random.uniform(0.8, 1.0)
                delay = max(delay, min(cfg.backoff_max, _retry_after(exc)))
                if deadline is not None and time.monotonic() + delay >= deadline:
                    raise self._out_of_time(attempt) from exc
                log.warning("LLM call to %s failed (%s: %s); retry %d/%d in %.2f s", cfg.model,
                            type(exc).__name__, _short(exc), attempt, cfg.max_retries, delay)
                self.usage.retries += 1
                self.usage.backoff_seconds += delay
                time.sleep(delay)
                continue
            return self._reply(response, attempt)

    def _out_of_time(self, requests: int) -> "LLMTimeoutError":
        cfg = self.config
        where = f" at {cfg.api_base}" if cfg.api_base else ""
        return LLMTimeoutError(f"{cfg.model}{where} gave no usable answer within max_seconds = {cfg.max_seconds:g} s "
                               f"({requests} request(s), retries and back-offs included); check the server, or raise "
                               "max_seconds in the llm config (--max-seconds)")

    def _reply(self, response, attempts: int) -> LLMReply:
        choice = response.choices[0]
        text = getattr(choice.message, "content", None) or ""
        usage = getattr(response, "usage", None)
        pt = int(getattr(usage, "prompt_tokens", 0) or 0)
        ct = int(getattr(usage, "completion_tokens", 0) or 0)
        cfg = self.config
        if cfg.input_cost_per_token is not None or cfg.output_cost_per_token is not None:
            cost = pt * (cfg.input_cost_per_token or 0.0) + ct * (cfg.output_cost_per_token or 0.0)
        else:
            try:
                cost = float(load_litellm().completion_cost(completion_response=response) or 0.0)
            except Exception:  # no price known for this model
                cost = 0.0
        return LLMReply(text, pt, ct, cost, False, getattr(response, "model", None) or cfg.model, attempts)

    def _error(self, error_cls: type[LLMError], exc: Exception, attempts: int) -> LLMError:
        cfg = self.config
        where = f"at {cfg.api_base}" if cfg.api_base else f"for {cfg.model}"
        tries = f"{attempts} attempt{'s' if attempts != 1 else ''}"
        detail = _short(exc)
        if error_cls is LLMConnectionError:
            target = cfg.api_base or f"the {cfg.model.split('/')[0]} endpoint"
            msg = (f"could not reach the model server at {target} ({tries}: {detail}); is the server running "
                   f"and is api_base right?")
        elif error_cls is LLMTimeoutError:
            msg = (f"{cfg.model} {where} gave no answer within the timeout of {cfg.timeout:g} s ({tries}); "
                   f"raise 'timeout' in the llm config or check the server's load")
        elif error_cls is LLMRateLimitError:
            msg = (f"{cfg.model} is still rate limited (429) after {attempts - 1} retries with backoff "
                   f"({detail}); wait, lower the request rate, or raise max_retries / backoff_max")
        elif error_cls is LLMServerError:
            msg = f"the model server {where} kept failing ({tries}): {detail}"
        elif error_cls is LLMAuthError:
            if cfg.api_key:
                source = "api_key in the llm config"
            elif cfg.api_key_env:
                source = f"the environment variable {cfg.api_key_env}"
            else:
                source = "the provider's key variable (e.g. GEMINI_API_KEY, OPENAI_API_KEY)"
            msg = f"{cfg.model} {where} rejected the API key ({detail}); check {source}"
        elif error_cls is LLMBadRequestError:
            msg = (f"{cfg.model} {where} rejected the request: {detail}; check the model name, the prompt "
                   f"length and the extra parameters")
        else:
            msg = f"calling {cfg.model} {where} failed: {type(exc).__name__}: {detail}"
        return error_cls(msg, attempts)


def _classify(exc: Exception) -> type[LLMError]:
    """The LLMError class (and so the retry policy) for a litellm exception."""
    litellm = load_litellm()
    text = str(exc)
    if isinstance(exc, litellm.Timeout):  # a subclass of APIConnectionError: test first
        return LLMTimeoutError
    if isinstance(exc, litellm.RateLimitError):
        return LLMRateLimitError
    if isinstance(exc, (litellm.AuthenticationError, litellm.PermissionDeniedError)):
        return LLMAuthError
    if "Missing credentials" in text or "api_key client option must be set" in text:
        return LLMAuthError
    if isinstance(exc, (litellm.BadRequestError, litellm.NotFoundError, litellm.UnprocessableEntityError,
                        litellm.UnsupportedParamsError)):
        return LLMBadRequestError
    if _is_connection_failure(exc):
        return LLMConnectionError
    status = getattr(exc, "status_code", None)
    if status == 429:
        return LLMRateLimitError
    if status == 408:
        return LLMTimeoutError
    if isinstance(exc, (litellm.InternalServerError, litellm.ServiceUnavailableError, litellm.BadGatewayError)):
        return LLMServerError
    if isinstance(status, int) and status >= 500:
        return LLMServerError
    if isinstance(status, int) and 400 <= status < 500:
        return LLMBadRequestError
    return LLMError


def _is_connection_failure(exc: BaseException) -> bool:
    """Connection refused / unreachable anywhere in the exception chain (litellm reports it as a 500)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        name = type(exc).__name__
        if isinstance(exc, (ConnectionError, OSError)) and not isinstance(exc, TimeoutError):
            return True
        if name in ("ConnectError", "APIConnectionError") or "Connection error" in str(exc):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def _retry_after(exc: Exception) -> float:
    """Seconds from a Retry-After header, 0 when none."""
    try:
        value = exc.response.headers.get("retry-after")  # type: ignore[attr-defined]
        return max(0.0, float(value))
    except Exception:
        return 0.0


def _short(exc: BaseException, limit: int = 300) -> str:
    """The exception's message without litellm's repeated class-name prefixes."""
    text = " ".join(str(exc).split())
    text = re.sub(r"^(?:(?:litellm\.)?\w+(?:Error|Exception|Timeout)\s*(?::|-)\s*)+", "", text)
    text = text or type(exc).__name__
    return text if len(text) <= limit else text[:limit] + "..."
