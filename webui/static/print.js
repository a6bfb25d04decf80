// The shift summary's Print button (a script file, not an onclick attribute, which the page's CSP forbids).
document.getElementById("print").addEventListener("click", () => window.print());
