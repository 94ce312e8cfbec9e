// /join/{slug}?PROLIFIC_PID=…: join the study, then go to the participant's page with
// location.replace, so that Back never returns here (and never joins twice).

import { Api, ApiError, connectionNotice } from "./api.js";

const heading = document.getElementById("join-heading");
const message = document.getElementById("join-message");

function fail(title, text) {
  document.title = title;
  heading.textContent = title;
  message.textContent = text;
  message.setAttribute("role", "alert");
  heading.focus();
}

async function join() {
  const slug = decodeURIComponent(location.pathname.split("/")[2] || "");
  const api = new Api({ onTrouble: connectionNotice(document.getElementById("connection")) });
  const query = location.search;
  try {
    const joined = await api.request("POST", `/api/studies/${encodeURIComponent(slug)}/join${query}`);
    location.replace(`/p/${encodeURIComponent(joined.token)}`);
  } catch (err) {
    if (!(err instanceof ApiError)) throw err;
    if (err.status === 404) {
      fail("Study not found", "There is no study at this address. Please check the link you were given.");
    } else if (err.status === 410) {
      fail("This study is closed", "This study is not taking new participants any more. Thank you for your interest.");
    } else {
      fail("Could not join the study", err.detail || `The server refused the request (status ${err.status}).`);
    }
  }
}

join();
