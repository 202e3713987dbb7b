"""LLM / LVLM reasoning backends: a local GGUF model (llama-cpp-python) or any OpenAI-compatible
chat endpoint (Ollama, vLLM, llama.cpp server), with the paper's reference view as an image.

Both ask for strict JSON {"object_name", "reason"} with the vocabulary in the prompt, parse it with
a JSON parser and a schema check (never eval), and fall back to the offline TextReasoner with the
reason logged and recorded whenever the answer is unusable (bad JSON, unknown object, timeout,
connection refused, HTTP error): a weak or unreachable model never stops grounding.
"""
from __future__ import annotations

import base64
import importlib.util
import json
import logging
import socket
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np

from ...config import MAX_QUERY_CHARS
from .explicit import explicit_match, normalise
from .gguf import llm_install_command, packaged_gguf
from ..base import BackendError
from . import Reasoner, Reasoning, validate
from .text import NAME_TEMPLATE, TextReasoner

log = logging.getLogger(__name__)
SYSTEM_PROMPT = (
    "You find the object a user means in a scene. The scene contains exactly these objects: {names}. "
    "Reply with one JSON object and nothing else: "
    '{{"object_name": "<one name from the list, spelled as in the list>", "reason": "<one short sentence>"}}.')


class AnswerError(ValueError):
    """A model answer is unusable; the message says why (shown as the fallback reason)."""


def image_data_url(image: np.ndarray) -> str:
    """RGB uint8 [H, W, 3] -> 'data:image/png;base64,...' (the OpenAI image_url content form)."""
    import cv2

    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image must be uint8 [H, W, 3] RGB, got {getattr(image, 'dtype', type(image))} "
                         f"{getattr(image, 'shape', '')}")
    ok, png = cv2.imencode(".png", image[:, :, ::-1])
    if not ok:
        raise ValueError("image could not be encoded as PNG")
    return "data:image/png;base64," + base64.b64encode(png.tobytes()).decode("ascii")


def build_messages(query: str, vocabulary: list[str], image_url: str | None = None) -> list[dict]:
    """Chat messages: the vocabulary and JSON format in the system prompt, the query (+ image)."""
    text = f"Query: {query.strip()}\nWhich object from the list does the query mean?"
    content: str | list = text
    if image_url:
        content = [{"type": "text", "text": "The image shows the scene. " + text},
                   {"type": "image_url", "image_url": {"url": image_url}}]
    return [{"role": "system", "content": SYSTEM_PROMPT.format(names=json.dumps(list(vocabulary)))},
            {"role": "user", "content": content}]


def answer_schema(vocabulary: list[str]) -> dict:
    return {"type": "object", "required": ["object_name", "reason"],
            "properties": {"object_name": {"type": "string", "enum": list(vocabulary)}, "reason": {"type": "string"}}}


def json_objects(text: str):
    """Balanced {...} spans of `text`, first first (models wrap JSON in prose or code fences);
    braces inside JSON strings are skipped."""
    start = text.find("{")
    while start >= 0:
        depth, in_str, esc = 0, False, False
        for i in range(start, len(text)):
            c = text[i]
            if in_str:
                esc, in_str = (False, True) if esc else (c == "\\", c != '"')
            elif c == '"':
                in_str = True
            elif c == "{":
                depth += 1
            elif c == "}":
                depth -= 1
                if depth == 0:
                    yield text[start:i + 1]
                    break
        start = text.find("{", start + 1)


def _load_json(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        first_error = exc.msg
    for span in json_objects(text):
        try:
            return json.loads(span)
        except json.JSONDecodeError:
            continue
    raise AnswerError(f"answer is not valid JSON ({first_error}) and holds no JSON object: {text[:120]!r}")


def json_object(text: str, expected: str = "an object") -> dict:
    """A model's answer text -> the JSON object in it; AnswerError when it is empty or holds none."""
    if not isinstance(text, str) or not text.strip():
        raise AnswerError("empty answer")
    data = _load_json(text)
    if not isinstance(data, dict):
        raise AnswerError(f"answer is JSON {type(data).__name__}, expected {expected}")
    return data


def parse_answer(text: str, vocabulary: list[str], text_model=None,
                 min_name_similarity: float = 0.8) -> tuple[str, str, float]:
    """Model answer -> (vocabulary name, reason, name-match score). The object_name must be a
    vocabulary name, the same ignoring case/articles/plurals (score 1), or, with a text model,
    nearer than `min_name_similarity` to one (score = that similarity)."""
    data = json_object(text, "an object with object_name and reason")
    missing = [k for k in ("object_name", "reason") if k not in data]
    if missing:
        raise AnswerError(f"answer lacks key(s) {missing}: {json.dumps(data)[:120]}")
    name, reason = data["object_name"], data["reason"]
    for key, v in (("object_name", name), ("reason", reason)):
        if not isinstance(v, str):
            raise AnswerError(f"answer's {key} is {type(v).__name__}, expected a string")
    if name in vocabulary:
        return name, reason, 1.0
    same = [v for v in vocabulary if normalise(v) == normalise(name) and normalise(name)]
    if same:
        return same[0], reason, 1.0
    if text_model is not None and name.strip():
        sims = (text_model([NAME_TEMPLATE.format(name)]) @ text_model([NAME_TEMPLATE.format(v) for v in vocabulary]).T)[0]
        i = int(sims.argmax())
        if float(sims[i]) >= min_name_similarity:
            return vocabulary[i], reason, float(sims[i])
    raise AnswerError(f"answer names {name!r}, which is not in the vocabulary")


class LLMReasoner(Reasoner):
    """Shared flow of the LLM backends: validation, explicit pass-through, prompt, parse, fallback."""

    name = "llm"

    def __init__(self, timeout_s: float = 30.0, max_query_chars: int = MAX_QUERY_CHARS, min_name_similarity: float = 0.8,
                 max_tokens: int = 96, fallback: TextReasoner | None = None, **text_kwargs):
        self.timeout_s, self.max_query_chars = float(timeout_s), max_query_chars
        self.min_name_similarity, self.max_tokens = min_name_similarity, max_tokens
        self.fallback = fallback or TextReasoner(max_query_chars=max_query_chars, **text_kwargs)

    def load(self) -> None:
        self.fallback.load()

    def complete(self, messages: list[dict], schema: dict, deadline: float) -> str:
        """The model's answer text, a JSON object meant to follow `schema`; raises AnswerError (or
        OSError/TimeoutError) when it has none."""
        raise NotImplementedError

    def ask_json(self, system: str, user: str, schema: dict) -> dict:
        """One structured question to the model: the JSON object it answers (not yet checked
        against `schema` beyond being an object). Raises AnswerError, OSError or TimeoutError;
        `describe` turns any of them into a reason."""
        if not isinstance(user, str) or not user.strip() or len(user) > self.max_query_chars:
            raise AnswerError(f"question must be 1-{self.max_query_chars} characters of text")
        text = self.complete([{"role": "system", "content": system}, {"role": "user", "content": user.strip()}],
                             schema, time.perf_counter() + self.timeout_s)
        return json_object(text)

    def image_url(self, image: np.ndarray | None) -> str | None:
        return None

    def reason(self, query: str, vocabulary: list[str], image: np.ndarray | None = None,
               mode: str = "auto") -> Reasoning:
        t0 = time.perf_counter()
        vocab = self.fallback.vocabulary(validate(query, vocabulary, self.max_query_chars, mode))
        if mode == "explicit" or (mode == "auto" and explicit_match(query, vocab)):
            r = self.fallback.reason(query, vocab, mode=mode)  # names pass straight through
            r.backend = self.name
            return r
        messages = build_messages(query, vocab, self.image_url(image))  # a bad image is the caller's error
        try:
            text = self.complete(messages, answer_schema(vocab), t0 + self.timeout_s)
            name, why, score = parse_answer(text, vocab, self.fallback.text, self.min_name_similarity)
        except Exception as exc:  # noqa: BLE001 - any failure of the model means: fall back
            reason = self.describe(exc)
            log.warning("%s reasoner: falling back to text: %s", self.name, reason)
            r = self.fallback.reason(query, vocab, mode="implicit")
            r.fallback_reason = reason
            r.explanation = f"{self.name} answer unusable ({reason}); fallback: {r.explanation}"
            r.seconds = time.perf_counter() - t0
            return r
        sim = float((self.fallback.text([query.strip()]) @ self.fallback.text([NAME_TEMPLATE.format(name)]).T)[0, 0])
        return Reasoning(name, f"{self.name} model chose {name!r}: {why}", score, True, self.name,
                         seconds=time.perf_counter() - t0, similarity=sim)

    def describe(self, exc: BaseException) -> str:
        if isinstance(exc, AnswerError):
            return str(exc)
        if isinstance(exc, (TimeoutError, socket.timeout)) or (
                isinstance(exc, urllib.error.URLError) and isinstance(exc.reason, (TimeoutError, socket.timeout))):
            return f"timeout: no answer within {self.timeout_s:g} s"
        if isinstance(exc, urllib.error.HTTPError):
            body = exc.read()[:200].decode("utf-8", "replace") if exc.fp else ""
            return f"HTTP error {exc.code} {exc.reason}: {body}"
        if isinstance(exc, urllib.error.URLError):
            return f"connection failed: {exc.reason}"
        if isinstance(exc, ConnectionError):
            return f"connection failed: {exc}"
        return f"{type(exc).__name__}: {exc}"


class OpenAIChatReasoner(LLMReasoner):
    """Any OpenAI-compatible /chat/completions endpoint, over urllib (no client library)."""

    name = "openai"

    def __init__(self, base_url: str = "http://127.0.0.1:8000/v1", model: str = "", api_key: str = "",
                 accepts_images: bool = False, json_mode: bool = True, **kwargs):
        super().__init__(**kwargs)
        if not base_url.startswith(("http://", "https://")):
            raise ValueError(f"base_url must start with http:// or https://, got {base_url!r}")
        self.url = base_url.rstrip("/") + "/chat/completions"
        self.model, self.api_key, self.accepts_images, self.json_mode = model, api_key, accepts_images, json_mode

    def image_url(self, image):
        return image_data_url(image) if image is not None and self.accepts_images else None

    def complete(self, messages, schema, deadline):
        body = {"model": self.model or "default", "messages": messages, "temperature": 0.0,
                "max_tokens": self.max_tokens}
        if self.json_mode:
            body["response_format"] = {"type": "json_object"}
        headers = {"Content-Type": "application/json"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        req = urllib.request.Request(self.url, json.dumps(body).encode(), headers, method="POST")
        with urllib.request.urlopen(req, timeout=max(1e-3, deadline - time.perf_counter())) as resp:
            raw = resp.read()
        try:
            return json.loads(raw)["choices"][0]["message"]["content"]
        except (ValueError, KeyError, IndexError, TypeError):
            raise AnswerError(f"malformed chat completion response: {raw[:120]!r}") from None


class LlamaCppReasoner(LLMReasoner):
    """A local GGUF model in-process (default: the packaged SmolLM2-135M; a LLaVA GGUF with its
    projector `clip_model_path` takes the reference image). The answer is constrained by a JSON
    schema grammar whose object_name is an enum of the vocabulary."""

    name = "llama_cpp"

    def __init__(self, model_path: str = "", clip_model_path: str = "", n_ctx: int = 2048, n_threads: int = 2,
                 **kwargs):
        super().__init__(**kwargs)
        if importlib.util.find_spec("llama_cpp") is None:
            raise BackendError("llama_cpp backend needs llama-cpp-python, which the demo install leaves out: "
                               f"install it with {llm_install_command()}")
        path = Path(model_path) if model_path else packaged_gguf()
        if not path.is_file():
            raise BackendError(f"llama_cpp: GGUF model file not found: {path}")
        from llama_cpp import Llama

        handler = None
        if clip_model_path:
            if not Path(clip_model_path).is_file():
                raise BackendError(f"llama_cpp: projector (clip_model_path) not found: {clip_model_path}")
            from llama_cpp.llama_chat_format import Llava15ChatHandler

            handler = Llava15ChatHandler(clip_model_path=str(clip_model_path), verbose=False)
        self.accepts_images = handler is not None
        self.llm = Llama(model_path=str(path), n_ctx=n_ctx, n_threads=n_threads, chat_handler=handler,
                         verbose=False)

    def image_url(self, image):
        return image_data_url(image) if image is not None and self.accepts_images else None

    def complete(self, messages, schema, deadline):
        # Streamed, so generation stops at the deadline (forcing EOS from a logits processor
        # clashes with the grammar and aborts the process; exceptions raised there are swallowed).
        stream = self.llm.create_chat_completion(
            messages=messages, temperature=0.0, max_tokens=self.max_tokens, stream=True,
            response_format={"type": "json_object", "schema": schema})
        parts = []
        for chunk in stream:
            if time.perf_counter() > deadline:
                stream.close()
                raise TimeoutError(f"generation passed {self.timeout_s:g} s")
            parts.append(chunk["choices"][0]["delta"].get("content") or "")
        return "".join(parts)
