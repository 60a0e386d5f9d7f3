// Entry point of index.html: reads the URL parameters, starts the player and publishes its
// test API as window.atgsPlayer (documented at Player.api in player.js).

import { Player, pageOptions } from './player.js';

const player = new Player(document, pageOptions(new URLSearchParams(location.search)));
window.atgsPlayer = player.api();
// anything that escapes the player still reaches the page: never a silent blank canvas
window.addEventListener('error', (e) => player.showError(e.message));
window.addEventListener('unhandledrejection', (e) => player.showError(e.reason?.message ?? String(e.reason)));
player.start();
