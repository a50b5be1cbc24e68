// @ts-check
// A WebSocket that reconnects with exponential back-off and says when it is lost.

import { tokenRefused, wsProtocols } from "./api.js";

const BACKOFF_MIN_MS = 500;
const BACKOFF_MAX_MS = 15000;

/**
 * @typedef {object} LostInfo
 * @property {number} code
 * @property {string} reason
 * @property {number} delay
 * @property {number} attempt
 */

/**
 * @template M
 * @typedef {object} StreamHandlers
 * @property {(message: M) => void} onMessage
 * @property {(state: "open" | "lost" | "ended", info?: LostInfo) => void} onState
 * @property {() => boolean} [shouldReconnect]
 */

/** @template M */
export class Stream {
  /**
   * @param {string} name what the stream is, in messages
   * @param {() => string} urlOf the address to (re)connect to, asked at every attempt
   * @param {StreamHandlers<M>} handlers
   */
  constructor(name, urlOf, handlers) {
    this.name = name;
    this.urlOf = urlOf;
    this.handlers = handlers;
    this.attempt = 0;
    /** @type {WebSocket | null} */
    this.ws = null;
    /** @type {number | undefined} */
    this.timer = undefined;
    this.closed = false;
  }

  open() {
    this.closed = false;
    clearTimeout(this.timer);
    const ws = new WebSocket(this.urlOf(), wsProtocols());
    this.ws = ws;
    ws.addEventListener("open", () => { this.attempt = 0; });
    ws.addEventListener("message", (event) => {
      if (ws !== this.ws) return;
      this.attempt = 0;
      this.handlers.onState("open");
      this.handlers.onMessage(JSON.parse(event.data));
    });
    ws.addEventListener("close", (event) => {
      if (ws !== this.ws || this.closed) return;
      this.ws = null;
      if (event.code === 1008) { // policy: the token was refused
        tokenRefused("The token was not accepted", `${this.name} stream closed: ${event.reason || "token refused"}`);
        return;
      }
      if (this.handlers.shouldReconnect && !this.handlers.shouldReconnect()) {
        this.handlers.onState("ended");
        return;
      }
      const delay = Math.min(BACKOFF_MAX_MS, BACKOFF_MIN_MS * 2 ** this.attempt);
      this.attempt += 1;
      this.handlers.onState("lost", { code: event.code, reason: event.reason, delay, attempt: this.attempt });
      this.timer = window.setTimeout(() => this.open(), delay);
    });
  }

  close() {
    this.closed = true;
    clearTimeout(this.timer);
    if (this.ws) {
      const ws = this.ws;
      this.ws = null;
      ws.close(1000);
    }
  }
}
